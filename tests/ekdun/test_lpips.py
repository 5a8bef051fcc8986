"""LPIPS is computed as published or reported "n/a" (ekdun.evaluation.metrics): the AlexNet
backbone is loaded strictly, the 'lpips' package's own linear layers are used, and a missing
or mismatched piece never gives a number from a random network."""

from __future__ import annotations

import sys
import types

import pytest
import torch
from torch import nn

from ekdun.evaluation.metrics import LPIPSMetric, alexnet_backbone_state

SHAPES = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3), 8: (256, 384, 3, 3),
          10: (256, 256, 3, 3)}


def _alexnet_state(seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    state = {}
    for i, shape in SHAPES.items():
        state[f"features.{i}.weight"] = torch.randn(shape, generator=gen) * 0.05
        state[f"features.{i}.bias"] = torch.randn(shape[0], generator=gen) * 0.05
    state["classifier.1.weight"] = torch.zeros(4, 4)          # not used by LPIPS: dropped
    return state


def test_backbone_state_maps_every_convolution_and_refuses_anything_else():
    mapped = alexnet_backbone_state(_alexnet_state(), "w.pth")
    assert sorted(mapped) == sorted(f"slice{s}.{i}.{p}" for i, s in
                                    zip(SHAPES, range(1, 6), strict=True)
                                    for p in ("weight", "bias"))
    torch.testing.assert_close(mapped["slice3.6.weight"], _alexnet_state()["features.6.weight"])
    missing = _alexnet_state()
    del missing["features.8.bias"]
    with pytest.raises(ValueError, match=r"w\.pth: not a torchvision AlexNet.*features\.8\.bias"):
        alexnet_backbone_state(missing, "w.pth")
    wrong = _alexnet_state()
    wrong["features.0.weight"] = torch.zeros(64, 3, 3, 3)
    with pytest.raises(ValueError, match="shape"):
        alexnet_backbone_state(wrong, "w.pth")
    renamed = {f"slice1.{k}": v for k, v in _alexnet_state().items()}   # lpips' own names
    with pytest.raises(ValueError, match="not a torchvision AlexNet"):
        alexnet_backbone_state(renamed, "w.pth")


class _FakeLPIPS(nn.Module):
    """Stands in for ``lpips.LPIPS`` (whose torchvision cannot be imported here): the same
    backbone layout (five slices keeping torchvision's layer indices) and a distance that
    depends on the backbone, so that a wrongly loaded backbone changes the result."""

    def __init__(self, net: str, version: str, pretrained: bool, pnet_rand: bool,
                 verbose: bool) -> None:
        super().__init__()
        assert (net, version, pretrained, pnet_rand) == ("alex", "0.1", True, True)
        self.net = nn.Module()
        for i, s in zip(SHAPES, range(1, 6), strict=True):
            block = nn.Sequential()
            block.add_module(str(i), nn.Conv2d(SHAPES[i][1], SHAPES[i][0], SHAPES[i][2]))
            self.net.add_module(f"slice{s}", block)
            torch.nn.init.constant_(block[0].weight, float("nan"))   # "random": never used

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        conv = self.net.slice1[0]
        return (conv(a) - conv(b)).pow(2).mean(dim=(1, 2, 3))


def test_lpips_is_computed_with_the_strictly_loaded_backbone(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "lpips", types.SimpleNamespace(LPIPS=_FakeLPIPS))
    weights = tmp_path / "alexnet.pth"
    torch.save(_alexnet_state(), weights)
    metric = LPIPSMetric(weights)
    assert metric.available and metric.reason == ""
    a, b = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    d = metric(a, b)
    assert torch.isfinite(d).all() and (d > 0).all()      # the NaN "random" init was replaced
    assert metric(a, a).abs().max() == 0
    # a file that is not AlexNet's weights: n/a with the reason, not a partly random network
    bad = _alexnet_state()
    del bad["features.10.weight"]
    torch.save(bad, tmp_path / "bad.pth")
    metric = LPIPSMetric(tmp_path / "bad.pth")
    assert not metric.available and "features.10.weight" in metric.reason
    assert torch.isnan(metric(a, b)).all()
