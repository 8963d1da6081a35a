# The searches the quality benches compare, by name: `search_flags NAME` sets the array `flags`
# to the `bench reconstruct` flags of that search. Sourced by quality.sh and quality-each.sh.
#
# likelihood-differential: the likelihood search with differential screening (CPU engine):
#   sweeps of 102 400 photons per source, confirmations of 204 800, up to 24 sweeps.
# likelihood-differential-direct8: the same, the direct renders of a sweep (changes it cannot
#   reweight) at an eighth of its photons (12 800).
# likelihood-differential-direct8-z2: the same, a change accepted for a confirmation at 2 paired
#   standard errors instead of 3.
# likelihood-differential-direct8-swaps: direct8 with neighbouring-pixel swaps in the sweeps.
# likelihood-differential-direct8-blocks: direct8 with 2 × 2 blocks and neighbouring pairs set
#   wholly to each material in the sweeps.
# likelihood-differential-direct8-simplify: direct8 with simplification rounds at 1 paired
#   standard error where the stage would end.
# likelihood-differential-direct8-blocks-simplify: direct8 with both.
# likelihood-differential-direct8-coarseN: direct8 with the coarse stage cut to its first N
#   quad-tree levels (coarse1: refinement from the one-material map).
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
    likelihood-differential-direct8-z2)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800 --set refine_z=2) ;;
    likelihood-differential-direct8-swaps)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800 --set refine_swaps=true) ;;
    likelihood-differential-direct8-blocks)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800 --set refine_blocks=true) ;;
    likelihood-differential-direct8-simplify)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800 --set refine_simplify_z=1) ;;
    likelihood-differential-direct8-blocks-simplify)
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800 --set refine_blocks=true
             --set refine_simplify_z=1) ;;
    likelihood-differential-direct8-coarse[1-9])
      flags=(--search likelihood --set refine_screen=differential --set refine_photons=102400
             --set refine_confirm_photons=204800 --set refine_sweeps=24
             --set refine_direct_photons=12800 --set "coarse_levels=${1##*-coarse}") ;;
    likelihood-direct8)
      flags=(--search likelihood --set refine_screen=direct --set refine_photons=12800
             --set refine_confirm_photons=204800 --set refine_sweeps=24) ;;
    paper) flags=(--search paper --iterations 8 --photons-per-iteration 512 --permutations 1) ;;
    *) flags=(--search "$1") ;;
  esac
}
