r"""The forward model with the scene on the whole padded grid, as the ADMM-TV solver uses it."""

from __future__ import annotations

from ekdun.errors import TensorShapeError
from psfkit.forward.operator import PaddedSceneOperator


class ExtendedSceneOperator(PaddedSceneOperator):
    """:class:`~psfkit.forward.operator.PaddedSceneOperator` raising ekdun's
    :class:`~ekdun.errors.TensorShapeError` from :meth:`check`."""

    shape_error = TensorShapeError
