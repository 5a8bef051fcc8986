"""research/precision_check.py (issue 45): the float32 reference is float32, the autocast run
is under autocast, and the differences are the PSNRs' own."""

from __future__ import annotations

import json

import pytest
import torch
from torch import nn

from ekdun.evaluation.metrics import psnr
from research import precision_check as pc


class _Mixer(nn.Module):
    """A 1×1 convolution (autocast runs it in half precision) after an elementwise step
    (which stays in float32)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv = nn.Conv2d(3, 3, 1, bias=False)
        with torch.no_grad():
            self.conv.weight.copy_(torch.eye(3)[:, :, None, None] * 0.9
                                   + 0.1 / 3 * torch.ones(3, 3, 1, 1))

    def forward(self, y: torch.Tensor) -> torch.Tensor:
        return self.conv(y * 1.0001)


def _pairs(n: int = 3) -> list[tuple[torch.Tensor, torch.Tensor]]:
    gen = torch.Generator().manual_seed(0)
    return [(torch.rand(3, 16, 16, generator=gen),
             torch.rand(3, 16, 16, generator=gen)) for _ in range(n)]


@pytest.mark.parametrize("amp", ["bf16", "fp16"])
def test_the_gap_is_autocast_against_float32(amp: str) -> None:
    model, pairs = _Mixer(), _pairs()
    gap = pc.precision_gap(model, pairs, amp)
    dtype = torch.bfloat16 if amp == "bf16" else torch.float16
    for (x, y), row in zip(pairs, gap["pairs"], strict=True):
        with torch.no_grad():
            full = model(y[None]).clamp(0, 1)
            with torch.autocast("cpu", dtype=dtype):
                half = model(y[None])
        half = half.float().clamp(0, 1)
        assert row["psnr_fp32"] == pytest.approx(float(psnr(full, x[None])[0]), abs=1e-9)
        assert row[f"psnr_{amp}"] == pytest.approx(float(psnr(half, x[None])[0]), abs=1e-9)
        assert row["delta_db"] == pytest.approx(row[f"psnr_{amp}"] - row["psnr_fp32"])
        # half precision really ran: the outputs differ, by its rounding (bf16 8 bits of
        # mantissa, fp16 11) and no more
        assert 35 < row["agreement_db"] < (70 if amp == "bf16" else 90)
    assert gap["max_abs_delta_db"] == max(abs(r["delta_db"]) for r in gap["pairs"])


def test_a_float32_only_network_loses_nothing() -> None:
    class Elementwise(nn.Module):
        def forward(self, y: torch.Tensor) -> torch.Tensor:
            return y * 0.5 + 0.25

    gap = pc.precision_gap(Elementwise(), _pairs(), "bf16")
    assert gap["max_abs_delta_db"] == 0.0


def test_a_missing_checkpoint_is_one_line(tmp_path, capsys) -> None:
    (tmp_path / "pairs").mkdir()
    code = pc.main([str(tmp_path / "out"), str(tmp_path / "none.pt"), "--pairs",
                    str(tmp_path / "pairs")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and not (tmp_path / "out" / "precision.json").exists()


def test_the_report_is_written(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(pc, "PairsDataset", lambda root: _pairs(2))
    monkeypatch.setattr(pc, "network_from_checkpoint",
                        lambda path: (_Mixer(), {"metadata": {"model": "mixer"}}))
    result = pc.precision_check(tmp_path, ["a.pt"], "pairs", ["bf16"])
    doc = json.loads((tmp_path / "precision.json").read_text())
    assert doc == json.loads(json.dumps(result)) and doc["n_pairs"] == 2
    assert "| a.pt | bf16 |" in (tmp_path / "precision.md").read_text()


def test_the_float32_reference_runs_without_tf32_and_restores_it() -> None:
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    seen = []

    class Probe(nn.Module):
        def forward(self, y: torch.Tensor) -> torch.Tensor:
            seen.append((torch.backends.cudnn.allow_tf32,
                         torch.backends.cuda.matmul.allow_tf32, torch.is_autocast_enabled("cpu")))
            return y

    try:
        torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = True
        pc.precision_gap(Probe(), _pairs(1), "bf16")
        # the float32 pass without TF32; the autocast pass as the network runs it
        assert seen == [(False, False, False), (True, True, True)]
        assert torch.backends.cudnn.allow_tf32 and torch.backends.cuda.matmul.allow_tf32
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def test_a_device_this_machine_lacks_is_one_line(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    (tmp_path / "pairs").mkdir()
    code = pc.main([str(tmp_path / "out"), str(tmp_path / "a.pt"), "--pairs",
                    str(tmp_path / "pairs"), "--device", "cuda"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "CUDA is not available" in err[0]
    assert not (tmp_path / "out").exists()
