#!/usr/bin/env python3
"""Prints the quality table (markdown) from the JSON that quality.sh and quality-each.sh write:
one row per (scene, search) with the mean pixel accuracy over its seeds, the level-0 map's,
photons, wall seconds, the truth check's z and the wrong pixels the target tells and does not
(a search whose targets have other than 200 000 photons per source is named with them, and a
run of quality-each.sh's TAG by it in brackets), and
the runs that were stopped (their logs end with "stopped after").
Usage: python3 tests/bench/quality-table.py [FILE.json|DIR]..."""
import json
import pathlib
import re
import sys

paths = [pathlib.Path(p) for p in sys.argv[1:]] or [pathlib.Path(__file__).parent / "quality"]
files = []
for p in paths:
    files += sorted(p.glob("*.json")) if p.is_dir() else [p]
runs_of = {}
for f in files:
    d = json.loads(f.read_text())
    name = d["search"]
    settings = d.get("set", [])
    # The recipe's name as searches.sh spells it, from the settings that differ.
    if "refine_screen=direct" in settings and "refine_photons=12800" in settings:
        name += "-direct8"
    for key, part in [("refine_screen=differential", "differential"),
                      ("refine_direct_photons=12800", "direct8"), ("refine_z=2", "z2"),
                      ("refine_swaps=true", "swaps"), ("refine_blocks=true", "blocks"),
                      ("refine_simplify_z=1", "simplify"), ("refine_grow=true", "grow")]:
        if key in settings:
            name += "-" + part
    name += "".join("-coarse" + s.split("=", 1)[1] for s in settings if s.startswith("coarse_levels="))
    # Targets of other than the bench's 200 000 photons per source are named by their photons.
    target = (d.get("configuration") or {}).get("target_photons", 200000)
    if target != 200000:
        name += f" (targets {target // 1000} k)"
    # A TAG of quality-each.sh (another build of the same recipe) ends the file's name.
    tag = re.search(r"-seeds[0-9-]+(?:-target[0-9]+)?-(?!target[0-9]+$)([^0-9-].*)$", f.stem)
    if tag:
        name += f" [{tag.group(1)}]"
    for r in d["runs"]:
        runs_of.setdefault((r["scene"], name), []).append(r)
def wrong(r):
    """The run's wrong pixels, and how many of them the target tells (the truth beats its
    neighbour with that pixel wrong by 2 standard errors: the search missed it) and does not
    (information), where the bench estimated them."""
    if r.get("wrong_pixels") is None:
        return "?"
    if r.get("wrong_told") is None:
        return f"{r['wrong_pixels']}"
    return f"{r['wrong_pixels']} ({r['wrong_told']}/{r['wrong_untold']})"


rows = []
for (scene, name), runs in runs_of.items():
    mean = lambda k: sum(r[k] for r in runs) / len(runs)
    rows.append((scene, name, len(runs), mean("pixel_accuracy"), mean("level0_pixel_accuracy"),
                 mean("photons") / 1e9, mean("wall_seconds"),
                 ", ".join(f"{r['truth_margin_z']:.1f}" for r in runs),
                 ", ".join(wrong(r) for r in runs)))
stopped = []
for p in paths:
    for log in (sorted(p.glob("*.log")) if p.is_dir() else []):
        if "stopped after" in log.read_text(errors="replace"):
            stopped.append(log.stem)
print("| scene | search | seeds | accuracy | level 0 | G photons | seconds | truth z "
      "| wrong (told/untold) |")
print("|---|---|---|---|---|---|---|---|---|")
for r in sorted(rows):
    print(f"| {r[0]} | {r[1]} | {r[2]} | {100*r[3]:.1f} % | {100*r[4]:.1f} % | {r[5]:.2f} | {r[6]:.0f} | {r[7]} | {r[8]} |")
for s in stopped:
    print(f"| {s} | stopped at the time limit | | | | | | | |")
