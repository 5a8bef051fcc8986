"""psfkit fit-eigen from the command line."""

import json

import pytest

from psfkit.cli import main
from psfkit.forward.kernelfile import load_kernels


def test_fit_eigen_writes_a_kernel_file_and_figures(grid_3x3, tmp_path, capsys):
    out, figures = tmp_path / "kernels.npz", tmp_path / "figs"
    assert main(["fit-eigen", str(grid_3x3), "--out", str(out), "--figures", str(figures),
                 "--folds", "4", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "fitted basis 'paper' (base, v, h)" in text and "centre PSF only" in text
    model = load_kernels(out)
    assert model.kernels.shape == (3, 3, 135, 180)
    assert model.convention == "sensor" and model.basis == "paper"
    assert model.provenance["fit"]["cross_validation"]["folds"] == 4
    for name in ("fig7_kernels", "fig7_kernels_zoom", "fig3_weights", "diagnostics"):
        assert (figures / f"{name}.pdf").is_file()
    summary = json.loads((figures / "fit.json").read_text())
    assert set(summary["in_sample_relative_error"]) == {"sensor", "source"}


def test_fit_eigen_source_convention_and_richer_basis(grid_3x3, tmp_path):
    out = tmp_path / "k.npz"
    assert main(["fit-eigen", str(grid_3x3), "--out", str(out), "--basis", "paper+odd",
                 "--convention", "source", "--cv-bases", "none", "--quiet"]) == 0
    model = load_kernels(out)
    assert model.kernel_names == ("base", "v", "h", "v_odd", "h_odd")
    assert model.convention == "source"


@pytest.mark.parametrize("argv,message", [
    (["--basis", "poly:3"],
     "basis 'poly:3' needs at least 10 positions (10 kernels) but only 9 remain"),
    (["--basis", "papr"], "unknown weight basis 'papr'"),
    (["--out", "{tmp}/k.txt"], "k.txt: kernel files are .npz"),
])
def test_fit_eigen_refusals(grid_3x3, tmp_path, capsys, argv, message):
    argv = [a.format(tmp=tmp_path) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(tmp_path / "k.npz")]
    assert main(["fit-eigen", str(grid_3x3), *argv, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "k.npz").exists()


def test_singular_design_is_refused(tmp_path, capsys):
    from psfkit.simulate import BenchConfig, simulate_grid

    row = simulate_grid(tmp_path / "row", BenchConfig(downsample=8), grid_shape=(1, 5),
                        progress=False)
    assert main(["fit-eigen", str(row), "--out", str(tmp_path / "k.npz"), "--quiet"]) == 2
    assert "singular design: the weight of kernel 'v'" in capsys.readouterr().err
