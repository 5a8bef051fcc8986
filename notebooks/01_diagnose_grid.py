# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 1. Diagnose the shift-variance of a PSF grid
#
# A lensless camera's PSF changes over the field: it shifts (that part a convolution handles),
# loses light (gain), and its caustic deforms (what a single shift-invariant kernel cannot
# describe). This notebook measures all three on a PSF grid and writes the report a lab reads
# before choosing a forward model (paper, Sec. 4.1 and Fig. 2).
#
# We use the **virtual bench** (a simulated diffuser camera whose true PSFs are known) so the
# notebook runs anywhere in seconds. With a measured grid, replace `grid_dir` by its folder
# (format: `docs/grid-format.md`). Command-line equivalent: `psfkit report GRID --out DIR`.

# %%
import os
from pathlib import Path

from IPython.display import display

from psfkit.characterization.characterize import CharacterizeOptions, characterize_grid
from psfkit.io import read_grid
from psfkit.report.figures import figure_maps, figure_shift_variance
from psfkit.report.grid import write_report
from psfkit.simulate import BenchConfig, read_ground_truth, simulate_grid

OUT = Path(os.environ.get("EKDUN_NB_OUT", "notebook_outputs")) / "01_diagnose_grid"
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## A small simulated grid
# 5 × 5 point-source positions over the whole field of view, the default camera binned 8×
# (135 × 180 pixels), with a dark frame and realistic noise. `ground_truth/` holds what a lab
# cannot know (true shifts and gains).

# %%
grid_dir = simulate_grid(OUT / "grid", BenchConfig(downsample=8), grid_shape=(5, 5),
                         overwrite=True, progress=False)
grid = read_grid(grid_dir)
print(grid.grid_shape, grid.image_shape, grid.channels)

# %% [markdown]
# ## Characterize: registration, gain, MAE, warp

# %%
result = characterize_grid(grid, CharacterizeOptions())
fit = result.shift_fit
print(f"magnification {fit.magnification:.2f} px per field unit, rms residual distortion "
      f"{fit.rms_residual:.3f} px")
centre_column = [p for p in result.positions if p.col == result.center[1]]
for p in centre_column:
    print(f"row {p.row}: shift (du, dv) = ({p.shift[0]:7.2f}, {p.shift[1]:7.2f}) px, "
          f"gain {p.gain:.3f}, MAE {p.mae:.2e}")

# %% [markdown]
# The true chief-ray shifts of the bench, for comparison:

# %%
truth = read_ground_truth(grid_dir)
print(truth.shift_px[:, result.center[1]])

# %% [markdown]
# ## Fig. 2: the breakdown of shift invariance
# Centre PSF (A), two off-axis PSFs on the centre column (B, C), their differences from A
# after shift compensation, and the MAE against position: the shift-invariant error grows
# towards the periphery.

# %%
display(figure_shift_variance(result))

# %%
display(figure_maps(result))

# %% [markdown]
# ## The report
# One self-contained HTML page with every figure, plus `results.json` and `positions.csv`.

# %%
report = write_report(result, OUT / "report", overwrite=True)
print(sorted(p.name for p in report.iterdir()))
print("open", (report / "report.html").resolve())
