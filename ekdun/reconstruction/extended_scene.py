r"""The forward model with the scene on the whole padded grid, as the ADMM-TV solver uses it.

:class:`psfkit.forward.operator.PaddedSceneOperator` (the operator of a kernel file, built in
one place; the maths is in its docstring) with ekdun's input error: a measurement that does not
fit the model raises :class:`~ekdun.errors.TensorShapeError`.
"""

from __future__ import annotations

from ekdun.errors import TensorShapeError
from psfkit.forward.operator import PaddedSceneOperator


class ExtendedSceneOperator(PaddedSceneOperator):
    """:class:`~psfkit.forward.operator.PaddedSceneOperator` raising ekdun's
    :class:`~ekdun.errors.TensorShapeError` from :meth:`check`
    (``ExtendedSceneOperator.from_kernel_model(model, dtype)`` builds it from a kernel file)."""

    shape_error = TensorShapeError
