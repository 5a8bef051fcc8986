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
# # 3. Did the network learn the physics? Learned vs measured kernels
#
# The paper (Sec. 5.6, Fig. 7) shows that the difference kernels `Kv − Kbase` and
# `Kh − Kbase` of a trained EK-DUN look like sub-pixel displacements of the caustic spots.
# `psfkit.compare` measures those displacements (dense optical flow, on the caustic) and
# compares them with what the PSF grid of the same camera says: the eigen-kernels fitted to
# the grid, the warps between the centre and the edge PSFs, and the grid's PCA modes.
# Command-line equivalent: `psfkit compare LEARNED.npz GRID --out DIR --initial START.npz`;
# see `docs/compare.md` for what each number means.
#
# > **Stand-in.** Training (`ekdun train`) is not part of this notebook yet. The "learned"
# > kernels below are a **stand-in made by perturbing the measured fit** (weaker differences,
# > noise, a small global shift), so the numbers show how to read the comparison, not what a
# > trained network learns. Replace `learned` by the kernel file a training run exports.

# %%
import os
from pathlib import Path

import numpy as np
from IPython.display import display
from scipy import ndimage

from psfkit.bench import BenchConfig, simulate_grid
from psfkit.compare import CompareOptions, compare_kernels, measure_modes
from psfkit.compare_report import write_comparison
from psfkit.figures.compare_figures import figure_displacements, figure_learned_vs_measured
from psfkit.io import read_grid
from psfkit.kernelfile import KernelModel, save_kernels
from psfkit.registration import shift_image

OUT = Path(os.environ.get("EKDUN_NB_OUT", "notebook_outputs")) / "03_compare"
OUT.mkdir(parents=True, exist_ok=True)
rng = np.random.default_rng(0)

# %% [markdown]
# ## The measured side
# A 3 × 3 grid of the virtual bench over 80 % of the field (the edge PSFs must overlap the
# centre one for a warp). `measure_modes` fits the eigen-kernels with the learned file's basis
# and convention, measures the warps of the edge PSFs and the PCA of the registered grid, once;
# several kernel files can then be compared with it.

# %%
grid = read_grid(simulate_grid(OUT / "grid", BenchConfig(downsample=8), grid_shape=(3, 3),
                               extent=0.8, overwrite=True, progress=False))
options = CompareOptions()
modes = measure_modes(grid, "paper", "sensor", grid.image_shape[1:], options)
print("warp positions used:", {k: [(p["row"], p["col"]) for p in v]
                               for k, v in modes.warp_positions.items()})
measured = modes.model.kernels

# %% [markdown]
# ## Stand-in "learned" and "initial" kernel files
# *Initial*: what EK-DUN starts from when seeded with a single measured PSF
# (`Kv = Kh = Kbase`). *Learned* (stand-in): the measured fit with 70 % of its differences,
# smoothed noise on the differences and a 0.3 px global shift.

# %%
base = measured[0]
noise = ndimage.gaussian_filter(rng.standard_normal(measured.shape), (0, 0, 1, 1))
noise *= 0.2 * np.abs(measured[1:] - base).mean() / np.abs(noise).mean()
learned_kernels = base + 0.7 * (measured - base) + noise * (np.arange(3) > 0)[:, None, None, None]
learned_kernels = shift_image(learned_kernels.reshape(-1, *base.shape[-2:]), (0.3, -0.2))[0]
learned = KernelModel(kernels=learned_kernels.reshape(measured.shape), basis="paper",
                      convention="sensor", sensor_shape=modes.sensor_shape,
                      provenance={"source": "notebook 03 stand-in: perturbed measured fit"})
initial = KernelModel(kernels=np.stack([base] * 3), basis="paper", convention="sensor",
                      sensor_shape=modes.sensor_shape)
save_kernels(OUT / "learned_standin.npz", learned)
save_kernels(OUT / "initial.npz", initial)

# %% [markdown]
# ## Compare

# %%
comparison = compare_kernels(learned, modes, initial=initial, options=options)
print("global shift of the learned Kbase (px):", np.round(comparison.learned.global_shift_px, 3))
for label, row in comparison.headline().items():
    print(label, {k: (None if v != v else round(v, 3)) for k, v in row.items()})
for name, a in comparison.measured_kernels_vs_warp.items():
    print(f"ceiling: measured K_{name} vs measured warp corr {a['corr']:.3f}")
print("principal angles learned vs measured eigen-kernels (deg):",
      np.round(comparison.learned.angles_eigen_deg, 1))
print("principal angles learned vs top-3 PCA modes (deg):",
      np.round(comparison.learned.angles_pca_deg, 1))

# %% [markdown]
# How to read it: the *initial* kernels have no displacement, so their correlations are
# undefined (`None`) — nothing has been learned. A learned `Kv` whose displacement map
# correlates with the measured one (and with the warp-predicted one) moved toward the measured
# mode; the slope says whether the amplitude matches (1 = same size of displacement).

# %%
display(figure_learned_vs_measured(comparison, zoom=0.3))
display(figure_displacements(comparison))

# %% [markdown]
# ## Write the comparison (figures, `compare.json`, `compare.html`)

# %%
folder = write_comparison(comparison, OUT / "comparison", overwrite=True)
print(sorted(p.name for p in folder.iterdir()))
print(sorted(p.name for p in (folder / "figures").iterdir()))
