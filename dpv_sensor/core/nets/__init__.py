"""Learned parts of dpv_sensor: D-Net (features + cost volume), K-Net, R-Net, presets, checkpoints.

    from dpv_sensor.core.nets import DPVNet, get_preset, load_checkpoint, default_weights_path
    net, meta = load_checkpoint(default_weights_path('lite'), preset='lite')

torch only (no ROS imports). See model.py for the call interface and presets.py for the presets.
"""
from dpv_sensor.core.nets.checkpoint import (CheckpointError, default_weights_path, load_checkpoint, read_metadata,
                                             save_checkpoint)
from dpv_sensor.core.nets.dnet import CostVolume, FeatureExtractor, ImageFeatures, feature_intrinsics, feature_size
from dpv_sensor.core.nets.knet import KNet
from dpv_sensor.core.nets.model import DPVNet, count_macs, count_parameters, cpu_bf16_fast
from dpv_sensor.core.nets.presets import PRESETS, Preset, get_preset, preset_names
from dpv_sensor.core.nets.rnet import RNet, upsample_logp

__all__ = [
    'DPVNet', 'FeatureExtractor', 'CostVolume', 'KNet', 'RNet', 'ImageFeatures', 'Preset', 'PRESETS',
    'get_preset', 'preset_names', 'feature_intrinsics', 'feature_size', 'upsample_logp',
    'save_checkpoint', 'load_checkpoint', 'read_metadata', 'default_weights_path', 'CheckpointError',
    'count_parameters', 'count_macs', 'cpu_bf16_fast',
]
