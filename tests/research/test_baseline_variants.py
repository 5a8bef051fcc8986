"""research/baseline_variants.py (issue 45): each variant changes exactly the reference's
choice it names, for its own training only, and the study pairs it with our network by seed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ekdun.data.virtual_bench import VirtualBenchSpec
from ekdun.nets.builder import build_network, seed_kernel_model
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.nets.configs import get_preset
from ekdun.nets.le_admm_u import LeADMMU
from ekdun.nets.updn import UPDN
from ekdun.training.trainer import CHECKPOINT, TrainOptions
from research import baseline_variants as bv


def _psf(size: int = 16) -> np.ndarray:
    rng = np.random.default_rng(0)
    psf = rng.random((3, size, size)).astype(np.float32) ** 8
    return psf / psf.sum(axis=(1, 2), keepdims=True)


def _unet_inputs(model: torch.nn.Module, y: torch.Tensor) -> torch.Tensor:
    seen = []
    handle = model.denoiser.register_forward_hook(lambda _m, args, _out: seen.append(args[0]))
    with torch.no_grad():
        model(y)
    handle.remove()
    return seen[0]


def test_the_normalised_variant_feeds_the_unet_images_of_peak_one_and_is_undone_after():
    torch.manual_seed(0)
    model = build_network("le-admm-u", seed_kernel_model(_psf()), "tiny")
    y = torch.rand(2, 3, 16, 16) * torch.tensor([1.0, 5.0])[:, None, None, None]
    ours = _unet_inputs(model, y)
    with bv.applied(bv.VARIANTS["le-admm-u-normalised"]):
        normalised = _unet_inputs(model, y)
    # the same ADMM image, each over its own maximum (the reference's normalize_image)
    peaks = ours.flatten(1).amax(dim=1)
    assert torch.allclose(normalised, ours / peaks[:, None, None, None], rtol=1e-6)
    assert torch.allclose(normalised.flatten(1).amax(dim=1), torch.ones(2))
    assert LeADMMU.__dict__["output"] is not bv._normalised_output


def test_the_sigmoid_variant_squashes_updns_output_and_is_undone_after():
    torch.manual_seed(0)
    model = build_network("updn", seed_kernel_model(_psf()), "tiny")
    y = torch.rand(1, 3, 16, 16)
    with torch.no_grad():
        linear = model(y)
        with bv.applied(bv.VARIANTS["updn-sigmoid"]):
            squashed = model(y)
    assert torch.allclose(squashed, torch.sigmoid(linear), atol=1e-6)
    assert UPDN.__dict__["output"] is not bv._sigmoid_output


@pytest.mark.parametrize("label, prefixes, scale", [
    ("updn-unet-fast", ("denoiser.",), 2.0),
    ("updn-blocks-slow", ("dual_updates.", "primal_updates."), 0.25)])
def test_a_rate_variant_moves_exactly_its_part_of_updn_to_its_rate(label, prefixes, scale):
    from ekdun.training import trainer

    model = build_network("updn", seed_kernel_model(_psf()), "tiny")
    plain = trainer._param_groups(model, 1e-3, 1e-2)
    with bv.applied(bv.VARIANTS[label]):
        groups = trainer._param_groups(model, 1e-3, 1e-2)
    assert trainer._param_groups is bv._PARAM_GROUPS
    rate = {id(p): g["lr"] for g in groups for p in g["params"]}
    expected = {id(p): g["lr"] for g in plain for p in g["params"]}
    assert rate.keys() == expected.keys()                    # every parameter, once
    assert sum(len(g["params"]) for g in groups) == len(rate)
    for name, p in model.named_parameters():
        want = expected[id(p)] * (scale if name.startswith(prefixes) else 1.0)
        assert rate[id(p)] == pytest.approx(want), name
    assert any(name.startswith(prefixes) for name, _p in model.named_parameters())


def test_a_method_is_restored_when_the_training_fails():
    original = LeADMMU.__dict__["output"]
    with pytest.raises(RuntimeError), bv.applied(bv.VARIANTS["le-admm-u-normalised"]):
        raise RuntimeError("training died")
    assert LeADMMU.__dict__["output"] is original


@pytest.mark.e2e
@pytest.mark.slow
def test_the_study_pairs_each_variant_with_our_network_by_seed(tmp_path):
    spec = VirtualBenchSpec(sensor_shape=(16, 16), n_train=4, n_test=2)
    options = TrainOptions(epochs=1, progress=False, threads=1)
    doc = bv.variants_check(tmp_path, spec, ["updn", "updn-5", "updn-psf-rate"], [0, 1],
                            options, log=lambda text: None)
    psnr = {(r["label"], r["seed"]): r["psnr"] for r in doc["rows"]}
    entry = next(e for e in doc["summary"]["updn"] if e["label"] == "updn-5")
    gaps = [psnr[("updn-5", s)] - psnr[("updn", s)] for s in (0, 1)]
    assert entry["delta_mean"] == pytest.approx(np.mean(gaps))
    # updn-5 is UPDN with five iterations: fewer update blocks, the same everything else
    params = {r["label"]: r["parameters"] for r in doc["rows"]}
    assert params["updn-5"] < params["updn"]
    assert "Δ to ours" in (tmp_path / "variants.md").read_text()
    # updn-psf-rate trained its PSFs at the network's rate, updn at the preset's fraction
    scale = {label: load_checkpoint(tmp_path / "runs" / f"{label}-s0" / CHECKPOINT)
             ["metadata"]["training"]["kernel_lr_scale"] for label in ("updn", "updn-psf-rate")}
    assert scale == {"updn": get_preset("tiny").training.kernel_lr_scale, "updn-psf-rate": 1.0}


def test_the_reference_unet_has_the_reference_size_and_replaces_le_admm_us_for_its_run():
    # UNet270480 counted from its layer list (docs/baselines.md): 11,772,307 parameters
    unet = bv.ReferenceUNet(3, (24, 64, 128, 256, 512))
    assert sum(p.numel() for p in unet.parameters()) == 11_772_307
    assert unet.eval()(torch.rand(1, 3, 35, 50)).shape == (1, 3, 35, 50)   # odd sizes come back
    seed = seed_kernel_model(_psf())
    with bv.applied(bv.VARIANTS["le-admm-u-reference"]):
        model = build_network("le-admm-u", seed, "tiny")
    assert isinstance(model.denoiser, bv.ReferenceUNet)
    assert not isinstance(build_network("le-admm-u", seed, "tiny").denoiser, bv.ReferenceUNet)
