"""photometric_evidence (training.self_supervised): which pixels enter the evidence's mean, each rule just either
side of its line, with the values worked out by hand.

A pixel counts when its best plane's error is *strictly* below the error of the sources left unwarped (it moves: a
static pixel, where every plane is as good as no warp, says nothing about depth) and below _FAR = 1e3 (the error
given to a source the pixel does not reach). Two planes, p = (0.5, 0.5), sigma = 1: a pixel whose planes err
(e, e + ln 3) has evidence -ln(0.5 + 0.5 / 3) = ln 1.5; one whose planes err alike has evidence 0; one whose second
plane reaches no source (1e3) has -ln(0.5 + 0.5 e^-1e4) = ln 2.
"""
import math

import pytest
import torch

from dpv_sensor.training import self_supervised as S

LN3, LN15, LN2 = math.log(3.0), math.log(1.5), math.log(2.0)


def evidence(pixels):
    """photometric_evidence of a 1 x n image, pixels [(error of plane 0, error of plane 1, unwarped error)]."""
    e = torch.tensor([[p[0] for p in pixels], [p[1] for p in pixels]], dtype=torch.float64).view(1, 2, 1, -1)
    identity = torch.tensor([p[2] for p in pixels], dtype=torch.float64).view(1, 1, -1)
    logp = torch.full_like(e, math.log(0.5))
    return S.photometric_evidence(logp, e, identity, 1.0).item()


@pytest.mark.parametrize('pixels, expected', [
    ([(0.0, LN3, 1.0)], LN15),                                   # moves: counted
    ([(0.25, 0.25 + LN3, 0.25)], 0.0),                           # best plane ties with no warp: static, left out
    ([(0.25, 0.25 + LN3, 0.2500001)], LN15),                     # just below the unwarped error: counted
    ([(0.25, 0.25 + LN3, 0.2499999)], 0.0),                      # just above: left out
    ([(0.1, 0.1, 1.0), (0.25, 0.25 + LN3, 0.25)], 0.0),          # the tie stays out of the mean: (0) / 1
    ([(0.0, LN3, 1.0), (0.1, 0.1, 1.0)], LN15 / 2),              # two moving pixels: (ln 1.5 + 0) / 2
    ([(0.0, LN3, 1.0), (0.1, 0.1, 1.0), (0.5, 0.5 + LN3, 0.5)], LN15 / 2),   # a third, static: still / 2
    ([(0.0, 1e3, 1.0)], LN2),                                    # plane 1 reaches no source
    ([(1e3, 1e3, 2e3)], 0.0),                                    # no plane reaches a source: left out
    ([(998.0, 998.0 + LN3, 2e3)], LN15),                         # both planes under _FAR: counted
    ([(999.0, 999.0 + LN3, 2e3)], LN2),                          # plane 1 (1000.1) over it: reaches no source
])
def test_which_pixels_enter_the_evidence(pixels, expected):
    assert evidence(pixels) == pytest.approx(expected, abs=1e-9)


def test_a_static_pixel_gives_no_gradient():
    """Where the best plane only ties with no warp, the DPV's probabilities get no gradient from it."""
    logits = torch.tensor([0.3, -0.2]).double().view(1, 2, 1, 1).requires_grad_(True)
    e = torch.tensor([0.25, 0.25 + LN3], dtype=torch.float64).view(1, 2, 1, 1)
    S.photometric_evidence(torch.log_softmax(logits, 1), e, torch.full((1, 1, 1), 0.25, dtype=torch.float64),
                           1.0).backward()
    assert logits.grad.abs().max() == 0.0
