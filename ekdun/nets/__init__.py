"""Unrolled reconstruction networks: EK-DUN and the Le-ADMM-U and UPDN baselines.

``build_model(name, kernel_file_or_psf, preset)`` builds any of them; see
:mod:`ekdun.nets.configs` for the ``tiny`` and ``paper`` presets.
"""

from ekdun.nets.configs import (
    PRESETS,
    EKDUNConfig,
    LeADMMUConfig,
    Preset,
    UNetConfig,
    UPDNConfig,
    get_preset,
    parse_schedule,
)
from ekdun.nets.ekdun_net import EKDUN
from ekdun.nets.factory import MODEL_NAMES, build_model
from ekdun.nets.le_admm_u import LeADMMU
from ekdun.nets.unet import UNet
from ekdun.nets.unrolled import UnrolledNetwork, count_parameters
from ekdun.nets.updn import UPDN

__all__ = ["EKDUN", "MODEL_NAMES", "PRESETS", "UPDN", "EKDUNConfig", "LeADMMU", "LeADMMUConfig",
           "Preset", "UNet", "UNetConfig", "UPDNConfig", "UnrolledNetwork", "build_model",
           "count_parameters", "get_preset", "parse_schedule"]
