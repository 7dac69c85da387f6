"""Torch linear operators of the camera model, each with an exact adjoint."""

from capssim.operators.analyzer import Analyzer, ChannelMix, ChannelSelect, analyzer_matrix
from capssim.operators.base import (
    Adjoint,
    Composition,
    LinearOperator,
    Multiply,
    Reshape,
    Stack,
    adjointness_error,
    operator_norm_estimate,
)
from capssim.operators.blur import Convolve
from capssim.operators.blur_sample import BlurIntegrateDecimate
from capssim.operators.camera import (
    caps_raw_operator,
    dofp_raw_operator,
    lr_channel_matrix,
    lr_observation_operator,
    lr_sampling_operator,
)
from capssim.operators.cfa import BayerMosaic, BayerSplit, ChannelSample, DoFPMosaic
from capssim.operators.sampling import Decimation, IntegrateDecimate, PixelIntegration
from capssim.operators.warp import Warp, warp_image

__all__ = [
    "Adjoint", "Analyzer", "BayerMosaic", "BayerSplit", "BlurIntegrateDecimate", "ChannelMix", "ChannelSample", "ChannelSelect",
    "Composition", "Convolve", "Decimation", "DoFPMosaic", "IntegrateDecimate", "LinearOperator", "Multiply",
    "PixelIntegration", "Reshape", "Stack", "Warp", "adjointness_error", "analyzer_matrix",
    "caps_raw_operator", "dofp_raw_operator", "lr_channel_matrix",
    "lr_observation_operator", "lr_sampling_operator", "operator_norm_estimate",
    "warp_image",
]
