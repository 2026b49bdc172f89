"""A Markdown table of ceiling files (experiments/ceiling.py): per file, the stream, the labels, the solved count
at each width, the mean time of the solved cases and the search's minutes.

    python experiments/ceiling_table.py results/ceiling/*.json > results/ceiling/README.md
"""

from __future__ import annotations

import argparse

from crowdrl.evaluation.ceiling import read_ceiling
from crowdrl.tables import markdown_table


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="+", help="ceiling files")
    a = p.parse_args(argv)
    rows = []
    for path in a.files:
        try:
            c = read_ceiling(path)
        except ValueError as exc:
            p.error(str(exc))
        n = c.counts()
        widths = ", ".join(f"{w}: {k}" for w, k in c.solved_by_width.items())
        rows.append([c.scenario, f"{c.split} seed {c.seed}", c.cases, n["solved"], n["infeasible"], n["unknown"],
                     f"{n['solved'] / c.cases:.3f}", f"{c.mean_time():.2f}", widths, f"{c.seconds / 60:.1f}"])
    print("# Ceilings: what is possible on each case (docs/ceiling.md)\n")
    print("Made by `python experiments/ceiling.py env=<scenario> out=results/ceiling/<scenario>.json` on one core of "
          "the 2-core CPU (grid cell 0.125 m, exhaustive proof to 3 steps; each width on the cases the narrower ones "
          "left unsolved, as listed); this table by `python experiments/ceiling_table.py results/ceiling/*.json`.\n")
    print(markdown_table(["scenario", "stream", "cases", "solved", "infeasible", "unknown", "ceiling success",
                          "mean time (s)", "solved by width (cumulative)", "minutes"], rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
