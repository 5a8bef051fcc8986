"""Fig. 3 of the paper (the weight maps ``1 − Wh − Wv``, ``Wv``, ``Wh``).

Usage::

    python analysis/fig3_weight_maps.py [--kernels K.npz | --basis B --sensor H W] --out DIR

With a kernel file, its basis and sensor size are used; otherwise ``--basis`` (default
``paper``) on a ``--sensor H W`` grid (default the paper's 1080 × 1440). Writes
``DIR/fig3_weight_maps.png|pdf`` and ``DIR/fig3.json`` (basis, sensor, the weights' ranges).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import run, write_json

from psfkit.forward.kernelfile import load_kernels
from psfkit.forward.weights import get_basis
from psfkit.io import atomic_directory
from psfkit.report.figures import figure_weight_maps, save_figure


def main(args: argparse.Namespace) -> int:
    if args.kernels:
        model = load_kernels(args.kernels)
        basis, sensor = model.basis, tuple(model.sensor_shape)
    else:
        basis, sensor = args.basis, tuple(args.sensor)
    weights = get_basis(basis)
    maps = weights.maps(sensor)
    names = list(weights.kernel_names)
    with atomic_directory(args.out, overwrite=args.overwrite) as tmp:
        save_figure(figure_weight_maps(basis, sensor), tmp / "fig3_weight_maps")
        write_json(tmp / "fig3.json", {
            "basis": basis, "sensor_shape": sensor, "source": args.kernels,
            "ranges": {n: [float(m.min()), float(m.max())] for n, m in zip(names, maps,
                                                                         strict=True)}})
    print(f"Fig. 3: weight maps of basis {basis!r} on a {sensor[0]}x{sensor[1]} sensor; "
          f"wrote {args.out}")
    return 0


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kernels", help="kernel file whose basis and sensor size to use")
    p.add_argument("--basis", default="paper", help="weight basis (default paper)")
    p.add_argument("--sensor", type=int, nargs=2, default=(1080, 1440), metavar=("H", "W"),
                   help="sensor size (default 1080 1440)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true")
    return p


if __name__ == "__main__":
    sys.exit(run(parser(), main))
