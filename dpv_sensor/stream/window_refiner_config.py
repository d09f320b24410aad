"""The window refiner's configuration and the records it takes and returns: ``PoseRefinerConfig`` (partly from the
settings table), ``WindowKeyframe`` (one keyframe as the estimator hands it over) and ``RefinementResult`` (what one
window's refinement gives back). numpy only; no ROS. The refiner itself is :mod:`dpv_sensor.stream.window_refiner`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Hashable, List, Optional, Tuple

import numpy as np

from dpv_sensor import params as _params
from dpv_sensor.core import pose_uncertainty
from dpv_sensor.core.flow_rotation import FlowConfig
from dpv_sensor.core.keypoint_pose import KeypointConfig, KeypointPose
from dpv_sensor.core.odometry_covariance import OdometryCovariance
from dpv_sensor.core.photometric import AlignmentConfig, AlignmentResult
from dpv_sensor.stream.window_graph import OdometrySteps

__all__ = ['PoseRefinerConfig', 'WindowKeyframe', 'RefinementResult', 'PairMatches']


# ------------------------------------------------------------------------------------------------------------------
# Configuration and data
# ------------------------------------------------------------------------------------------------------------------

@dataclass
class PoseRefinerConfig:
    """Parameters of :class:`WindowPoseRefiner`.

    alignment: photometric alignment parameters (pyramid, robust norm, convergence tests).
    odom_sigma_rot_deg: rotation sigma of an odometry between factor (per keyframe step, degrees).
    odom_sigma_trans_m, odom_sigma_trans_rel: translation sigma of an odometry between factor:
        ``odom_sigma_trans_m + odom_sigma_trans_rel * |step translation|`` (metres).
    prior_sigma_rot_deg, prior_sigma_trans_m: the gauge prior on the oldest keyframe of the window.
    photometric_huber_k: Huber threshold (in sigmas) of the robust noise model of photometric factors.
    depth_scale_sigma: relative uncertainty of the predicted depth's overall scale; widens each photometric
        factor along its translation (the part of the translation the depth's scale decides; see
        :meth:`~dpv_sensor.core.photometric.AlignmentResult.between_covariance_gtsam`).
    inv_depth_offset_sigma: std (1/m) of a constant inverse-depth error of the predicted depth, which widens each
        photometric factor along the pose change such an error causes (mostly a rotation about the axis normal to
        the baseline: plane-swept depth from poses with rotation errors is off by about rotation error / baseline
        in inverse depth, and aligning against it would re-create those rotation errors). None: automatic,
        ``radians(odom_sigma_rot_deg) / |baseline to the nearest source|``.
    translation_sigma_rel: isotropic widening of the photometric translation, relative to the step length, for
        errors in the predicted depth's structure. With the filter's depth, photometric translations are only
        good to a few percent of the baseline (rotations to a few hundredths of a degree); with exact depth, about
        1-3 mm at 3-5 cm baselines (``studies.poses --parts gtcheck``), so sub-millimetre odometry errors are
        below what the alignment resolves.
    use_depth_uncertainty: in the estimator hook, derive the per-pixel inverse-depth std from the DPV confidence
        (:func:`~dpv_sensor.core.photometric.inverse_depth_std_from_confidence`) and let the alignment weigh it.
    max_sources: align the reference against at most this many sources (nearest in key order first);
        None = all sources of the window. The earlier alignments stay in the window (``keep_old_factors``), so
        2 keeps every window keyframe tied to two others at half the cost of 4 (measured on a rendered
        sequence with the classical model: rotation RPE 0.054 deg either way, abs_rel 0.166 vs 0.165,
        alignment 46 vs 86 ms per keyframe).
    keep_old_factors: keep earlier alignments between keyframes that are still in the window.
    min_converged_fraction: tracking is lost when fewer than this fraction of the alignments are usable
        (converged and no jump).
    require_nearest: tracking is lost when the alignment to the nearest source is not usable.
    max_jump_translation_m, max_jump_rotation_deg: pose-jump limits. An alignment that moves the relative pose
        further than this from its odometry initialisation is not used (a jump); and tracking is lost when the
        refined relative motion between consecutive keyframes differs from the odometry's by more than this.
    lm_max_iterations: Levenberg-Marquardt iterations of the window optimisation.
    warmup_keyframes: after a (re)start, the first this many references that come with a predicted depth are
        not aligned (odometry only): that depth has integrated few measurements, and aligning against a wrong
        depth makes the rotation consistent with it (rotation-translation ambiguity), locking the error in.
    max_rotation_parallax: a window is not refined (the odometry poses are kept, ``RefinementResult.skipped``
        says why) when the camera turns in place: the rotation to the nearest source (radians) is more than this
        many times the parallax its baseline gives at the predicted depth's median (baseline / depth). There the
        predicted depth carries little information and aligning against it moves the rotation away from the
        truth: on tum_fr1_rpy (median ratio 14.5 between keyframes) refinement doubled the rotation RPE against the
        motion-capture poses (0.16 -> 0.34 deg). The rendered selection scenes stay below 4.4, the SUN3D
        fragments below 7 (90th percentiles). 0 disables the rule.
    """
    alignment: AlignmentConfig = field(default_factory=lambda: AlignmentConfig(
        finest_level=1, num_levels=3, max_pixels=2000, step_tolerance=5e-4))
    odom_sigma_rot_deg: float = _params.default('odom_sigma_rot_deg')
    odom_sigma_trans_m: float = _params.default('odom_sigma_trans_m')
    odom_sigma_trans_rel: float = _params.default('odom_sigma_trans_rel')
    prior_sigma_rot_deg: float = 1e-3
    prior_sigma_trans_m: float = 1e-5
    photometric_huber_k: float = 3.0
    depth_scale_sigma: float = 0.05
    inv_depth_offset_sigma: Optional[float] = None
    translation_sigma_rel: float = 0.1
    use_depth_uncertainty: bool = True
    max_sources: Optional[int] = _params.default('refine_photometric_sources')
    keep_old_factors: bool = True
    min_converged_fraction: float = 0.5
    require_nearest: bool = True
    max_jump_translation_m: float = 0.10
    max_jump_rotation_deg: float = 5.0
    lm_max_iterations: int = 30
    warmup_keyframes: int = 0
    max_rotation_parallax: float = 8.0
    odom_covariance: str = _params.default('refine_odom_covariance')
    drift: pose_uncertainty.DriftModel = field(default_factory=lambda: pose_uncertainty.DriftModel(sync_s=0.0))
    keypoint_factors: bool = _params.default('refine_keypoints')
    keypoint: KeypointConfig = field(default_factory=KeypointConfig)
    keypoint_sources: int = 2
    keypoint_prior_gate_px: float = 0.0
    keypoint_huber_k: float = 1.345
    keypoint_scale_sigma_rel: float = 0.5
    keypoint_direction: str = _params.default('refine_keypoint_direction')
    rotation_evidence: str = _params.default('refine_rotation_evidence')
    flow: FlowConfig = field(default_factory=FlowConfig)
    flow_huber_k: float = 10.0
    flow_direction_ratio: float = _params.default('refine_flow_direction_ratio')
    flow_direction_pairs: int = 50
    flow_probe_every: int = 4
    marginals: bool = _params.default('refine_marginals')
    gate_chi2: float = _params.default('refine_gate_chi2')
    photometric_gate_chi2: float = _params.default('refine_photometric_gate_chi2')
    gate_min_inliers: int = _params.default('refine_gate_min_inliers')

    # Pose-error model of the window (defaults from the parameter table: odometry covariance and keypoints on,
    # no photometric factors; the plain photometric window of paper eq. 11 is odom_covariance='fixed',
    # keypoint_factors=False, max_sources=2; see :meth:`WindowPoseRefiner._optimize`):
    # odom_covariance: 'fixed' (the odom_sigma_* above) or 'odometry' (each step's covariance: the growth of the
    #     keyframes' published pose covariance where it grows, else their twist covariance integrated over the
    #     step, else the ``drift`` figures of the step; within the floor and the jump limits:
    #     window_graph.odometry_step_covariance).
    # keypoint_factors: add keypoint relative-pose factors (core.keypoint_pose) between the reference and its
    #     ``keypoint_sources`` nearest sources, Huber ``keypoint_huber_k``. keypoint_direction 'odometry': the
    #     rotation given the odometry's translation direction, the translation free (left to the odometry
    #     factors); 'keypoints': rotation and direction from the images, the translation's length from the
    #     odometry (``keypoint_scale_sigma_rel`` of it along the baseline).
    # rotation_evidence: what the rotation factors (keypoint_factors on) are measured from. 'keypoints': SIFT at
    #     the processing size, as above. 'flow': dense optical flow at the camera's resolution
    #     (core.flow_rotation), the rotation solved with the odometry's translation direction held fixed, between
    #     the reference and its ``keypoint_sources`` nearest sources; the factors of pairs that stay in the window
    #     are kept, so every pair of neighbouring keyframes is tied. Huber ``flow_huber_k``: their stds are a few
    #     hundredths of a degree, so a kernel at 1.345 sigmas would hand most of a 0.3 degree drift back to the
    #     odometry. 'auto': the flow factors while the median of the last ``flow_direction_pairs`` flow pairs'
    #     ``direction_ratio`` (core.flow_rotation) is at most ``flow_direction_ratio``, i.e. while the images agree
    #     with the odometry's translation directions, else the SIFT factors (decided per window; before any pair
    #     has a ratio, SIFT). Once a fifth of ``flow_direction_pairs`` have a ratio, the camera is settled: where
    #     their median says the images disagree, the flow is measured on every ``flow_probe_every``-th window only;
    #     where it says they agree, every window's flow is measured and every ``flow_probe_every``-th new pair
    #     also measures its ratio.
    # marginals: after the solve, each source's pose covariance relative to the reference (gtsam Marginals) in
    #     ``RefinementResult.source_sigma``, the pose uncertainty the estimator widens with in place of the
    #     odometry's.
    # gate_chi2 > 0: keep the odometry when a keypoint rotation differs from the odometry's by d with
    #     d^T (S_odom + S_kp)^-1 d above this (3 dof; 16.27 = 99.9 %). gate_min_inliers > 0 (with keypoint
    #     factors): keep the odometry when no keypoint pair has this many inliers (e.g. a textureless window).
    # photometric_gate_chi2 > 0: a photometric alignment enters only when its rotation correction d (from the
    #     odometry-chained pose) has d^T S^-1 d at most this, S the rotation covariance of the odometry between the
    #     source and the reference (odometry_step_covariance): a correction the odometry's own uncertainty cannot
    #     explain follows the depth being aligned against. Decided per alignment, not per window.

    #: node parameters (dpv_sensor.params) that set fields of this class: parameter name -> field name
    PARAMS = {'odom_sigma_rot_deg': 'odom_sigma_rot_deg', 'odom_sigma_trans_m': 'odom_sigma_trans_m',
              'odom_sigma_trans_rel': 'odom_sigma_trans_rel', 'refine_odom_covariance': 'odom_covariance',
              'refine_photometric_sources': 'max_sources', 'refine_keypoints': 'keypoint_factors',
              'refine_keypoint_direction': 'keypoint_direction', 'refine_rotation_evidence': 'rotation_evidence',
              'refine_flow_direction_ratio': 'flow_direction_ratio',
              'refine_marginals': 'marginals',
              'refine_gate_chi2': 'gate_chi2', 'refine_gate_min_inliers': 'gate_min_inliers',
              'refine_photometric_gate_chi2': 'photometric_gate_chi2'}

    @classmethod
    def photometric(cls, **kw) -> 'PoseRefinerConfig':
        """The plain photometric window (paper eq. 11): alignments to the two nearest sources and odometry factors
        with the fixed ``odom_sigma_*``, no keypoints; ``kw`` sets other fields."""
        return cls(**dict(dict(odom_covariance='fixed', keypoint_factors=False, max_sources=2), **kw))

    @classmethod
    def from_params(cls, values) -> 'PoseRefinerConfig':
        """The defaults, with the fields named in :attr:`PARAMS` taken from the node's parameter values; the drift
        figures (for ``odom_covariance='odometry'`` steps without a published covariance) from the odom_drift_*
        parameters."""
        kw = {f: type(getattr(cls, f))(values[k]) for k, f in cls.PARAMS.items() if k in values}
        if all(k in values for k in ('odom_drift_trans', 'odom_drift_rot_deg_per_m', 'odom_drift_rot')):
            kw['drift'] = pose_uncertainty.DriftModel(trans_per_m=float(values['odom_drift_trans']),
                                                      rot_deg_per_m=float(values['odom_drift_rot_deg_per_m']),
                                                      rot_per_deg=float(values['odom_drift_rot']), sync_s=0.0,
                                                      cov_trans_per_m=float(values['odom_drift_trans']))
        if 'refine_flow_max_width' in values:
            kw['flow'] = FlowConfig(max_width=int(values['refine_flow_max_width']))
        return cls(**kw)


@dataclass
class WindowKeyframe:
    """One keyframe of the window as the estimator hands it over.

    key: an identifier that orders keyframes in time (a keyframe counter or the stamp); the same keyframe must
        carry the same key in every call. image: uint8 HxWx3 RGB (or grey / float [0,1], any form
        :func:`~dpv_sensor.core.photometric.to_gray` takes), at the processing size. K_33: its intrinsics.
    T_world_cam_odom_44: the pose from odometry (or visual odometry); only its first value per key is used.
    pose_cov_66 / twist_cov_66: the odometry's pose and twist covariance there (ROS order; None: not filled) and
    stamp its time (s; the twist covariance is integrated over the time between keyframes): what the odometry
    factors' covariance is read from (``odom_covariance='odometry'``); only their first values per key are used.
    camera_image / camera_K_33: the image at the camera's own resolution and its intrinsics, what the flow
    rotation factors (``rotation_evidence='flow'``) match; None: ``image`` and ``K_33``.
    """
    key: Hashable
    image: object
    K_33: np.ndarray
    T_world_cam_odom_44: np.ndarray
    pose_cov_66: Optional[np.ndarray] = None
    twist_cov_66: Optional[np.ndarray] = None
    stamp: Optional[float] = None
    camera_image: object = None
    camera_K_33: Optional[np.ndarray] = None

    def odometry_covariance(self) -> Optional[OdometryCovariance]:
        """What the odometry says about itself at this keyframe (None when it says nothing)."""
        if self.pose_cov_66 is None and self.twist_cov_66 is None:
            return None
        as66 = lambda c: None if c is None else np.asarray(c, np.float64).reshape(6, 6)  # noqa: E731
        return OdometryCovariance(as66(self.pose_cov_66), as66(self.twist_cov_66), self.stamp)


@dataclass
class RefinementResult:
    """What :meth:`WindowPoseRefiner.refine` returns.

    T_world_cam: refined (or, after tracking loss, odometry-chained) pose of every window keyframe, by key.
    T_world_ref_44: the reference keyframe's pose (``T_world_cam[ref.key]``).
    T_src_ref: per source (in the order given) the relative pose for the plane sweep, ``T_src_ref = T_world_src^-1
        T_world_ref`` from the poses above.
    tracking_ok: False when the refinement diverged (see the module doc); reason says why (None when ok or when
        there was nothing to refine, e.g. no depth yet: then ``refined`` is False).
    refined: True when photometric factors entered the optimisation.
    alignments: per source (order given) the :class:`AlignmentResult` (None when not aligned).
    timings_ms: wall time of 'align' (the photometric alignments), 'keypoints' (detection, matching and the keypoint
        poses), 'optimize' (the rest: the gate, the solve, the marginals), 'total'; 'cpu': process CPU time of the
        call.
    skipped: why this window was not refined although it could have been (the camera turns in place: see
        ``PoseRefinerConfig.max_rotation_parallax``); the poses are then the odometry-chained ones, tracking is ok.
    """
    T_world_cam: Dict[Hashable, np.ndarray]
    T_world_ref_44: np.ndarray
    T_src_ref: List[np.ndarray]
    tracking_ok: bool
    reason: Optional[str]
    refined: bool
    alignments: List[Optional[AlignmentResult]]
    timings_ms: Dict[str, float] = field(default_factory=dict)
    skipped: Optional[str] = None
    source_sigma: Dict[Hashable, pose_uncertainty.PoseSigma] = field(default_factory=dict)
    gate: str = 'none'
    correction: Tuple[float, float] = (0.0, 0.0)
    keypoints: List[KeypointPose] = field(default_factory=list)
    # the solved graph's factors by kind, as key pairs: 'prior' (the gauge, (anchor, anchor)), 'odometry' (a, b),
    # 'photometric' (reference, source), 'keypoint' (source, reference); empty when nothing was solved
    factors: Dict[str, List[Tuple[Hashable, Hashable]]] = field(default_factory=dict)
    # the window's odometry factors: median per-axis std of a step and where its covariance came from
    odometry: Optional[OdometrySteps] = None
    # the matches the window measured between the reference and its sources (flow or SIFT), with the odometry's
    # uncertainty of each pair's relative pose: what the reference's metric anchors are triangulated from
    matches: List['PairMatches'] = field(default_factory=list)
    # the grey images the flow matched, by key (what the anchors' tracks are refined on); empty without the flow
    match_images: Dict[Hashable, np.ndarray] = field(default_factory=dict)


@dataclass
class PairMatches:
    """Matched pixels of two window keyframes: ``pa_n2`` in keyframe ``key_a`` and ``pb_n2`` in ``key_b``, at the size
    ``K_33`` belongs to (the flow's camera-resolution images or SIFT's processing-size ones); ``sigma_rot_rad`` /
    ``sigma_trans_m``: the per-axis std of the odometry's relative pose between the two (rotation, translation);
    ``flow_hw2``: with the flow, its dense field from a to b, which chains pairs into tracks."""
    key_a: Hashable
    key_b: Hashable
    pa_n2: np.ndarray
    pb_n2: np.ndarray
    K_33: np.ndarray
    sigma_rot_rad: float = 0.0
    sigma_trans_m: float = 0.0
    flow_hw2: Optional[np.ndarray] = None      # the flow's dense field from a to b (None: SIFT's inliers)
