"""Evaluation: metrics (PSNR, SSIM, LPIPS), model evaluation and Tables 1 and 2."""

from ekdun.evaluation.evaluate import evaluate_checkpoints, evaluate_model, evaluation_pairs
from ekdun.evaluation.metrics import LPIPSMetric, psnr, ssim
from ekdun.evaluation.tables import (
    read_results,
    render_table,
    write_results,
    write_table,
    write_tables,
)

__all__ = ["LPIPSMetric", "evaluate_checkpoints", "evaluate_model", "evaluation_pairs", "psnr",
           "read_results", "render_table", "ssim", "write_results", "write_table", "write_tables"]
