"""Fig. 2 of the paper (breakdown of shift invariance) from a measured PSF grid.

Usage::

    python analysis/fig2_shift_variance.py GRID --out DIR [--overwrite]

Writes ``DIR/fig2_shift_variance.png|pdf`` (centre PSF A, off-axis PSFs B, C on the centre
column, Diff(A−B), Diff(A−C) after shift compensation, MAE vs position) and ``DIR/fig2.json``
(per-position shift, gain and MAE along the centre column).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import run, write_json

from psfkit.characterization.characterize import CharacterizeOptions, characterize_grid
from psfkit.io import atomic_directory, read_grid
from psfkit.report.figures import figure_shift_variance, save_figure


def main(args: argparse.Namespace) -> int:
    grid = read_grid(args.grid, check_pixels=False)
    result = characterize_grid(grid, CharacterizeOptions(steps=("register", "gain", "mae")),
                               progress=not args.quiet)
    column = result.center[1]
    rows = [{"row": p.row, "col": p.col, "field_deg": p.field_deg, "shift_px": p.shift,
             "gain": p.gain, "mae": p.mae, "mae_gain_compensated": p.mae_gain_compensated}
            for p in result.positions if p.col == column]
    with atomic_directory(args.out, overwrite=args.overwrite) as tmp:
        save_figure(figure_shift_variance(result), tmp / "fig2_shift_variance")
        write_json(tmp / "fig2.json", {"grid": str(grid.root), "centre": result.center,
                                       "centre_column": rows,
                                       "mae": result.to_dict()["conventions"]["mae"]})
    mae = max(r["mae"] for r in rows)
    print(f"Fig. 2 of {grid.root}: largest MAE on the centre column {mae:.4g}; wrote {args.out}")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("grid", help="PSF-grid folder")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


if __name__ == "__main__":
    sys.exit(run(parser(), main))
