# The searches the quality benches compare, by name: `search_flags NAME` sets the array `flags`
# to the `bench reconstruct` flags of that search. Sourced by quality.sh and quality-each.sh.
#
# likelihood-differential: the likelihood search with differential screening (CPU engine):
#   sweeps of 102 400 photons per source, confirmations of 204 800, up to 24 sweeps.
# likelihood-differential-direct8: the same, the direct renders of a sweep (changes it cannot
#   reweight) at an eighth of its photons (12 800).
# likelihood-differential-direct8-PART-PART…: direct8 with these parts, in this order (the
#   name `quality-table.py` gives a run), each one setting:
#   z2        a change accepted for a confirmation at 2 paired standard errors instead of 3;
#   swaps     neighbouring-pixel swaps in the sweeps;
#   blocks    2 × 2 blocks and neighbouring pairs set wholly to each material in the sweeps;
#   simplify  simplification rounds at 1 paired standard error where the stage would end;
#   (Runs without `grow` or `nogrow` in their name had no growth rounds before stop 49; since
#   then the default, `auto`, runs them where the refinement starts from level 0's map.)
#   grow      growth rounds where the stage would end: small objects grown by their neighbours
#             and recoloured, each rendered on its own, the best tried when none wins
#             (refine_grow; runs before the trials: the untagged fig7f seed-1 JSON; before
#             the filled bounding boxes: tags trial and trialz; with them: tag rect);
#   nogrow    no growth rounds (refine_grow=false): the default refinement before stop 49, when
#             growth became `auto` (on where the refinement starts from level 0's map);
#   notrial   no growth trials: a growth round's best grown map is tried only above a paired
#             z of 1e9 (refine_grow_trial_z), so only rounds that win change the map;
#   coarseN   the coarse stage cut to its first N quad-tree levels (coarse1: refinement from
#             the one-material map); coarseauto: cut after level 0 where its material
#             scatters (`coarse_levels = "auto"`).
#   e.g. likelihood-differential-direct8-blocks-coarse1.
# likelihood-direct8: the likelihood search with direct screening (every change of a sweep
#   rendered) at 12 800 photons per source, an eighth of likelihood-differential's sweeps, the
#   same confirmations: what differential screening is measured against (issue 19).
# paper: the paper's search at its budget at this geometry, 4 096 photons per source per render.
# anything else: `--search NAME` with its defaults.
search_flags() {
  case "$1" in
    likelihood-differential)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24) ;;
    likelihood-differential-direct8)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800) ;;
    likelihood-differential-direct8-*)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800)
      local part
      for part in $(tr - ' ' <<<"${1#likelihood-differential-direct8-}"); do
        case "$part" in
          z2) flags+=(--set refine_z=2) ;;
          swaps) flags+=(--set refine_swaps=true) ;;
          blocks) flags+=(--set refine_blocks=true) ;;
          simplify) flags+=(--set refine_simplify_z=1) ;;
          grow) flags+=(--set refine_grow=true) ;;
          nogrow) flags+=(--set refine_grow=false) ;;
          notrial) flags+=(--set refine_grow_trial_z=1e9) ;;
          coarse[1-9] | coarseauto) flags+=(--set "coarse_levels=${part#coarse}") ;;
          *) echo "searches.sh: unknown part '$part' of $1 (z2, swaps, blocks, simplify, grow, nogrow, notrial, coarseN, coarseauto)" >&2
             return 1 ;;
        esac
      done ;;
    likelihood-direct8)
      flags=(--search likelihood --set refine_screen=direct --set refine_photons=12800
             --set refine_confirm_photons=204800 --set refine_sweeps=24) ;;
    paper) flags=(--search paper --iterations 8 --photons-per-iteration 512 --permutations 1) ;;
    *) flags=(--search "$1") ;;
  esac
}
