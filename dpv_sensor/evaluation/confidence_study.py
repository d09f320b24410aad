"""The analysis of the confidence study (``dpv_sensor.studies.confidence_features`` collects the samples): how well
each cue ranks right from wrong per sequence, and calibration maps on the cues scored leave-one-sequence-out.

Ranking, per sequence and pose source: the AUROC of the x1.25 event for each cue, oriented by its sign over all
sequences pooled (above 0.5 = ranks the way it does overall; a cue that carries stays above 0.5 everywhere), and the
frame-mean confident-half ratio (conf½) of the cue used as a confidence.

Maps, scored on a sequence they were not fitted on (both pose sources of the other real sequences and the fit
renders, each group weighted the same): ``raw`` (no map), ``isotonic`` (a monotone map of the confidence alone,
what ``calibrate`` fits), ``platt`` (a logistic map of the confidence's logit) and logistic maps on sets of cues
(``core.confidence_map``). Every figure of a real sequence is held out; the held-out renders are scored by maps
fitted on all real sequences and the fit renders.
"""
from __future__ import annotations

import pathlib
from typing import Dict, List, Sequence, Tuple

import numpy as np

from dpv_sensor.evaluation.calibration_fit import fit_logistic, isotonic_knots
from dpv_sensor.evaluation import metrics as M
from dpv_sensor.stream.confidence_features import FEATURES

__all__ = ['load_samples', 'auroc', 'frame_conf_half', 'run_study']

# cues ranked in the study (the per-pixel ones and the frame medians)
RANKED = FEATURES + ('depth', 'frame_confidence', 'frame_parallax_px', 'frame_texture', 'frame_photometric')
# pixels per (sequence, source) group a map is fitted on (drawn with replacement where a group has fewer, so each
# group weighs the same)
FIT_PIXELS = 40000
# renders used only to fit (never scored); the other rendered seeds are held out
FIT_RENDERS = ('synthetic_seed60', 'synthetic_seed61')
_CUES = ('logit_confidence', 'entropy', 'second_mode', 'log_parallax', 'log_texture', 'photometric', 'views',
         'log_innovation', 'first_keyframe', 'log_pose_sigma')
MODELS = {
    'platt': ('logit_confidence',),
    'compact': ('logit_confidence', 'second_mode', 'log_parallax', 'frame_log_parallax'),
    'cues': _CUES,
    'cues+depth': _CUES + ('log_depth',),
    'cues+frame': _CUES + ('frame_logit_confidence', 'frame_log_parallax', 'frame_log_texture', 'frame_photometric'),
}


def load_samples(folder: pathlib.Path, names: Sequence[str], sources: Sequence[str]
                 ) -> Dict[Tuple[str, str], Dict[str, np.ndarray]]:
    out = {}
    for n in names:
        for s in sources:
            p = pathlib.Path(folder) / f'{n}__{s}.npz'
            if p.is_file():
                with np.load(p) as z:
                    out[(n, s)] = {k: z[k] for k in z.files}
    return out


def auroc(score: np.ndarray, label: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for the positive ``label`` (ties share their rank); NaN scores are
    left out; NaN when a class is missing."""
    from scipy.stats import rankdata
    s = np.asarray(score, np.float64)
    y = np.asarray(label, bool)
    ok = np.isfinite(s)
    s, y = s[ok], y[ok]
    n1, n0 = int(y.sum()), int((~y).sum())
    if n1 == 0 or n0 == 0:
        return float('nan')
    r = rankdata(s)
    return float((r[y].sum() - n1 * (n1 + 1) / 2.0) / (n1 * n0))


def frame_conf_half(rel_err: np.ndarray, score: np.ndarray, keyframe: np.ndarray, min_pixels: int = 100) -> float:
    """Mean over keyframes (with at least ``min_pixels`` finite scores) of the confident-half ratio."""
    vals = []
    for k in np.unique(keyframe):
        m = (keyframe == k) & np.isfinite(score)
        if m.sum() >= min_pixels:
            vals.append(M.confident_half_ratio(rel_err[m], score[m]))
    vals = [v for v in vals if np.isfinite(v)]
    return float(np.mean(vals)) if vals else float('nan')


def _balanced(groups: List[Dict[str, np.ndarray]], pixels: int, seed: int = 0) -> Dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    parts = []
    for g in groups:
        n = g['hit'].size
        idx = rng.choice(n, pixels, replace=n < pixels)       # every group the same weight
        parts.append({k: v[idx] for k, v in g.items()})
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _scores(model: str, fit: Dict[str, np.ndarray], test: Dict[str, np.ndarray]) -> np.ndarray:
    if model == 'raw':
        return test['confidence'].astype(np.float64)
    if model == 'isotonic':
        xs, ys, _ = isotonic_knots(fit['confidence'].astype(np.float64), fit['hit'])
        return np.interp(test['confidence'].astype(np.float64), xs, ys)
    cmap = fit_logistic(fit, fit['hit'], MODELS[model])
    return cmap.apply(test)


def _summary(score: np.ndarray, s: Dict[str, np.ndarray]) -> Dict[str, float]:
    hit = s['hit'].astype(bool)
    kept = M.kept_at_thresholds(score, hit, (0.9,))['0.9']
    return {'ece': M.expected_calibration_error(score, hit), 'mean_confidence': float(np.mean(score)),
            'hit_rate': float(hit.mean()), 'conf_half': frame_conf_half(s['rel_err'], score, s['keyframe']),
            'kept09': kept['share'], 'delta1_09': kept['delta1']}


def run_study(folder: pathlib.Path, names: Sequence[str], sources: Sequence[str]) -> Dict:
    samples = load_samples(folder, names, sources)
    real = [n for n in names if not n.startswith('synthetic_')]
    held_renders = [n for n in names if n.startswith('synthetic_') and n not in FIT_RENDERS]
    # ranking
    pooled = {k: np.concatenate([g[k] for g in samples.values()]) for k in RANKED + ('hit',)}
    sign = {k: (1.0 if auroc(pooled[k], pooled['hit']) >= 0.5 else -1.0) for k in RANKED}
    ranking = {}
    for (n, s), g in samples.items():
        ranking[f'{n} {s}'] = {k: {'auroc': auroc(sign[k] * g[k], g['hit']),
                                   'conf_half': frame_conf_half(g['rel_err'], sign[k] * g[k], g['keyframe'])}
                               for k in RANKED}
    # maps, leave one sequence out; fitted with and without the fit renders
    models = ['raw', 'isotonic'] + list(MODELS)
    loso = {}
    for renders in (True, False):
        part = loso.setdefault('real + renders' if renders else 'real only', {})
        for held in real + held_renders:
            fit_names = [n for n in real if n != held] + ([n for n in FIT_RENDERS if n in names] if renders else [])
            fit = _balanced([samples[(n, s)] for n in fit_names for s in sources if (n, s) in samples], FIT_PIXELS)
            for s in sources:
                if (held, s) in samples:
                    test = samples[(held, s)]
                    part[f'{held} {s}'] = {m: _summary(_scores(m, fit, test), test) for m in models}
    # the map on everything (what would ship), its weights
    every = real + [n for n in FIT_RENDERS if n in names]
    full_fit = _balanced([samples[(n, s)] for n in every for s in sources if (n, s) in samples], FIT_PIXELS)
    shipped = {m: fit_logistic(full_fit, full_fit['hit'], MODELS[m]).to_dict() for m in MODELS}
    return {'json': {'sign': sign, 'ranking': ranking, 'loso': loso, 'maps': shipped},
            'markdown': _markdown(sign, ranking, loso, models)}


def _f(x, spec='.3f'):
    return '-' if x is None or not np.isfinite(x) else format(x, spec)


def _markdown(sign, ranking, loso, models) -> str:
    lines = ['## Ranking: AUROC of the x1.25 event per cue (oriented by the pooled sign; > 0.5 ranks as it does '
             'overall)', '']
    cues = list(RANKED)
    lines.append('| run | ' + ' | '.join(f"{'-' if sign[c] < 0 else ''}{c}" for c in cues) + ' |')
    lines.append('|---' * (len(cues) + 1) + '|')
    for run, r in ranking.items():
        lines.append(f'| {run} | ' + ' | '.join(_f(r[c]['auroc'], '.2f') for c in cues) + ' |')
    lines += ['', '## conf½ of each cue used as the confidence (frame mean; lower ranks better)', '']
    lines.append('| run | ' + ' | '.join(cues) + ' |')
    lines.append('|---' * (len(cues) + 1) + '|')
    for run, r in ranking.items():
        lines.append(f'| {run} | ' + ' | '.join(_f(r[c]['conf_half'], '.2f') for c in cues) + ' |')
    for fitted, rows in loso.items():
        lines += ['', f'## Maps held out (leave one sequence out; fitted on the other {fitted}): ECE / conf½ / '
                  'conf >= 0.9 share (delta1)', '']
        lines.append('| held out | ' + ' | '.join(models) + ' |')
        lines.append('|---' * (len(models) + 1) + '|')
        for run, r in rows.items():
            cells = [f"{_f(r[m]['ece'])} / {_f(r[m]['conf_half'], '.2f')} / {_f(r[m]['kept09'], '.0%')} "
                     f"({_f(r[m]['delta1_09'], '.2f')})" for m in models]
            lines.append(f'| {run} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines) + '\n'
