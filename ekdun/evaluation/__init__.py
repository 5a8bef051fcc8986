"""Evaluation: metrics (PSNR, SSIM, LPIPS), model evaluation and Tables 1 and 2."""

from ekdun.evaluation.evaluate import evaluate_model
from ekdun.evaluation.metrics import LPIPSMetric, psnr, ssim
from ekdun.evaluation.tables import write_tables

__all__ = ["LPIPSMetric", "evaluate_model", "psnr", "ssim", "write_tables"]
