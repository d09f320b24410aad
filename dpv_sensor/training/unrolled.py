"""The unrolled filter loss of one batch (paper sec. 3.3), shared by training and validation.

One training sample is a run of M = K + 4 consecutive keyframes (see :mod:`.dataset`). For each of
the K unrolled filter steps j the network measures the quarter-resolution DPV of step j's reference
from its five-frame window (D-Net), the filter ``DPVFilter(mode='knet', knet=model.knet)`` predicts the
previous belief into the new camera and fuses the measurement (K-Net), and R-Net upsamples the
filtered belief to full resolution. Gradients flow through all K steps, so K-Net is trained on the
situations it meets at run time (a warped prior that is right in most voxels and wrong at
disocclusions) and learns where to damp.

Loss (per sample, averaged over the batch)::

    L = 1/K sum_j NLL(R(filter_j), d_gt)  +  aux_weight * 1/K sum_j NLL(meas_j, d_gt at 1/4)

The first term is the paper's loss (NLL of the GT depth under the full-resolution DPV, at every
unrolled step). The second is an auxiliary NLL on D-Net's own quarter-resolution measurement: it
gives the feature extractor a direct gradient that does not have to pass through K-Net and R-Net
(both start near the identity) and keeps the measurement itself calibrated - the filter assumes a
calibrated likelihood. It speeds up learning in a short CPU budget; ``--aux-weight 0`` gives the
paper's loss exactly.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Sequence as Seq, Tuple

import torch
import torch.nn as nn

from dpv_sensor import params as _params
from dpv_sensor.core import dpv as dpvops
from dpv_sensor.core import geometry

__all__ = ['measure_steps', 'make_filter', 'quarter_gt', 'filter_steps', 'run_unrolled', 'UnrolledModel',
           'batch_to_device']


def batch_to_device(batch: Dict[str, torch.Tensor], device) -> Dict[str, torch.Tensor]:
    """The batch with its tensors on ``device`` (other values as they are)."""
    return {k: (v.to(device, non_blocking=True) if torch.is_tensor(v) else v) for k, v in batch.items()}


def _pick(x: torch.Tensor, idx: int) -> torch.Tensor:
    return x[:, idx]


def measure_steps(model, batch: Dict[str, torch.Tensor], steps: Optional[Seq[int]] = None) -> List[Dict]:
    """D-Net measurement of every unrolled step of a batch (see :mod:`.dataset` for the layout).

    Returns per step a dict: logp_q (B,D,h,w), K_vol, feats, image (B,3,H,W), gt (B,H,W; None for a batch
    without depths), T_world_ref (B,4,4), stamp (float), ref (keyframe index), sources (the keyframe indices used),
    T_src_ref (B,S,4,4).
    """
    from dpv_sensor.core.nets.dnet import ImageFeatures
    images, poses, K = batch['images'], batch['poses'], batch['K']
    ref_idx = batch['ref_idx'][0].tolist()
    src_idx = batch['src_idx'][0].tolist()
    B, M = images.shape[:2]
    # every keyframe's features once (a keyframe serves as reference and as source of several steps)
    fa = model.extract_features(images.reshape(B * M, *images.shape[2:]))
    fusion = fa.fusion.reshape(B, M, *fa.fusion.shape[1:])
    half = fa.half.reshape(B, M, *fa.half.shape[1:])
    out = []
    counts = batch['src_count'][0].tolist() if 'src_count' in batch else None
    for j in (range(len(ref_idx)) if steps is None else steps):
        r, ss = ref_idx[j], src_idx[j]
        if counts is not None:
            ss = ss[len(ss) - int(counts[j]):]
        ref = images[:, r]
        T_world_ref = poses[:, r]
        T_src_world = geometry.invert_se3(poses[:, ss].reshape(-1, 4, 4)).reshape(B, len(ss), 4, 4)
        T_src_ref = T_src_world @ T_world_ref[:, None]
        logp_q, K_vol, feats = model.measure(ref, None, K, T_src_ref, src_features=fusion[:, ss],
                                             ref_features=ImageFeatures(fusion[:, r], half[:, r]))
        out.append(dict(logp_q=logp_q, K_vol=K_vol, feats=feats, image=ref,
                        gt=batch['depths'][:, r] if 'depths' in batch else None,
                        T_world_ref=T_world_ref, stamp=float(batch['stamps'][0, r]), ref=r, sources=list(ss),
                        T_src_ref=T_src_ref))
    return out


def make_filter(model, mode: str, damping: float = _params.default('damping')):
    """A fresh DPVFilter in ``mode`` (K-Net = the model's, so gradients reach it)."""
    from dpv_sensor.core.filter import DPVFilter
    # generous reset thresholds: training windows never need a reset (and a reset would cut the unroll)
    return DPVFilter(mode=mode, damping=damping, knet=model.knet if mode == 'knet' else None,
                     max_time_gap=1e9, max_translation=1e9, max_rotation_deg=1e9)


def quarter_gt(gt_bhw: torch.Tensor, hw: Tuple[int, int]) -> torch.Tensor:
    """GT on the quarter-resolution DPV grid: volume pixel j sits on full-resolution pixel 4j."""
    h, w = hw
    return gt_bhw[:, ::4, ::4][:, :h, :w]


def filter_steps(model, meas: List[Dict], depths_d: torch.Tensor, mode: str, refine: bool = True) -> List[Dict]:
    """Run the filter over the measured steps and refine each belief; returns per step
    ``filtered_q`` (quarter-res log-DPV after the update) and ``logp_full`` (R-Net output)."""
    filt = make_filter(model, mode)
    out = []
    for m in meas:
        st = filt.step(m['logp_q'], m['K_vol'], m['T_world_ref'], m['stamp'], depths_d, image_b3hw=m['image'])
        res = dict(filtered_q=st.logp_bdhw, reset=st.reset_reason)
        if refine:
            res['logp_full'] = model.refine(st.logp_bdhw, m['feats'], m['image'])
        out.append(res)
    return out


def run_unrolled(model, batch: Dict[str, torch.Tensor], depths_d: torch.Tensor, aux_weight: float = 0.5,
                 mode: str = 'knet', measure_grad: bool = True) -> Tuple[torch.Tensor, Dict[str, float]]:
    """The training loss of one batch (see the module docstring) and scalar statistics.

    ``measure_grad=False`` runs D-Net without autograd (it is frozen) and drops the auxiliary term, which
    would then carry no gradient.
    """
    with torch.set_grad_enabled(measure_grad and torch.is_grad_enabled()):
        meas = measure_steps(model, batch)
    res = filter_steps(model, meas, depths_d, mode)
    nll_full, nll_q = [], []
    for m, r in zip(meas, res):
        nll_full.append(dpvops.nll(r['logp_full'].float(), depths_d, m['gt']))
        gq = quarter_gt(m['gt'], m['logp_q'].shape[-2:])
        nll_q.append(dpvops.nll(m['logp_q'].float(), depths_d, gq))
    l_full = torch.stack(nll_full).mean()
    l_q = torch.stack(nll_q).mean()
    loss = l_full + aux_weight * l_q if aux_weight > 0 and measure_grad else l_full
    stats = {'loss': float(loss.detach()), 'nll_full': float(l_full.detach()), 'nll_meas_q': float(l_q.detach()),
             'resets': sum(r['reset'] is not None for r in res[1:])}
    for j, v in enumerate(nll_full):
        stats[f'nll_full_{j}'] = float(v.detach())
    return loss, stats


class UnrolledModel(nn.Module):
    """nn.Module wrapper whose forward is the whole unrolled loss (what DDP wraps)."""

    def __init__(self, model: nn.Module, depths_d: torch.Tensor, aux_weight: float, measure_grad: bool = True):
        super().__init__()
        self.model = model
        self.register_buffer('depths_d', depths_d, persistent=False)
        self.aux_weight = float(aux_weight)
        self.measure_grad = bool(measure_grad)

    def forward(self, batch: Dict[str, torch.Tensor]):
        loss, stats = run_unrolled(self.model, batch, self.depths_d, self.aux_weight, measure_grad=self.measure_grad)
        return loss, stats
