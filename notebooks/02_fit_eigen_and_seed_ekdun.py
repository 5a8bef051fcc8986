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
# # 2. Fit eigen-kernels and seed EK-DUN
#
# The paper's forward model (Eq. 7) writes the shift-variant PSF as a weighted sum of three
# kernels, `Kbase`, `Kv`, `Kh`, with fixed weight maps. Here we fit those kernels to a PSF
# grid in closed form (`psfkit fit-eigen`), write the **kernel file** (the hand-off between
# measuring and learning), and build an EK-DUN from it whose kernels start at the measured
# values. Command-line equivalent: `psfkit fit-eigen GRID --out kernels.npz --figures DIR`.

# %%
import os
from pathlib import Path

import numpy as np
import skimage.data
import skimage.transform
import torch
from IPython.display import display

from ekdun.nets import build_model
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.fitting.pairs.fit import predict
from psfkit.forward.kernelfile import load_kernels, save_kernels
from psfkit.io import read_grid
from psfkit.report.figures import figure_eigen_diagnostics, figure_kernels, figure_weight_maps
from psfkit.report.figures.style import new_figure
from psfkit.simulate import BenchConfig, simulate_grid

OUT = Path(os.environ.get("EKDUN_NB_OUT", "notebook_outputs")) / "02_fit_eigen"
OUT.mkdir(parents=True, exist_ok=True)
torch.manual_seed(0)

# %% [markdown]
# ## A PSF grid (virtual bench, 5 × 5 positions over 80 % of the field)

# %%
grid = read_grid(simulate_grid(OUT / "grid", BenchConfig(downsample=8), grid_shape=(5, 5),
                               extent=0.8, overwrite=True, progress=False))

# %% [markdown]
# ## Fit the eigen-kernels
# Both weight conventions are fitted (sensor-side: Eq. 7 as written; source-side: weights of
# the source position) and compared by leave-positions-out cross-validation with the
# shift-invariant model.

# %%
result = fit_eigen_grid(grid, EigenFitOptions(basis="paper", convention="sensor", folds=5))
for name, err in result.cv["held_out_relative_error"].items():
    print(f"{name:24s} held-out relative error {err:.4f}")
print("principal angles eigen-kernels vs top-3 PCA modes (deg):",
      np.round(result.angles_deg, 1))
display(figure_eigen_diagnostics(result))

# %% [markdown]
# ## The kernel file

# %%
kernel_file = save_kernels(OUT / "kernels.npz", result.kernel_model())
model = load_kernels(kernel_file)
print(model.kernel_names, model.kernels.shape, model.convention, model.sensor_shape)

# %% [markdown]
# Fig. 7 layout for the *measured* kernels, and the weight maps (Fig. 3):

# %%
display(figure_kernels(model.kernels, model.kernel_names, "measured eigen-kernels"))
display(figure_weight_maps(model.basis, model.sensor_shape))

# %% [markdown]
# ## Seed an EK-DUN with the measured kernels
# `build_model("ekdun", kernel_file, preset)` takes every kernel of the file as a trainable
# initial value; the sensor size is the file's. The `tiny` preset has the paper's architecture
# (10 iterations, eigen-kernel model in the last 2) and is meant for CPU experiments.

# %%
net = build_model("ekdun", model, "tiny")
print(f"{net.parameter_count():,} trainable parameters", net.parameter_breakdown())
kernels = net.physics.kernels.detach().numpy()
print("kernels in the network equal the file's:", np.allclose(kernels, model.kernels))

# %% [markdown]
# ## One forward pass on a simulated measurement
# The measurement is simulated with the same eigen-kernel forward model. The network is
# untrained, so its output is not yet a good reconstruction: training (`ekdun train`) is what
# turns this into Fig. 6.

# %%
scene = skimage.transform.resize(skimage.data.astronaut(), model.sensor_shape,
                                 anti_aliasing=True).astype(np.float32)
x = np.moveaxis(scene, -1, 0)[None]
y = predict(model, x)
with torch.no_grad():
    estimate = net(torch.as_tensor(y)).numpy()
print("measurement", y.shape, "reconstruction", estimate.shape)
fig = new_figure(7.2, 2.2)
for ax, (img, title) in zip(fig.subplots(1, 3), [(x[0], "scene"), (y[0], "measurement"),
                                                 (estimate[0], "untrained EK-DUN")],
                            strict=True):
    ax.imshow(np.clip(np.moveaxis(img, 0, -1) / max(float(img.max()), 1e-12), 0, 1))
    ax.set_title(title)
    ax.set_axis_off()
display(fig)
