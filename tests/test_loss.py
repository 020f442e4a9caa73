"""SPI loss on a worked example (eqs. 10-18)."""
import math

import pytest
import torch

from pipeline.lib.learning.loss import SPILoss, data_loss, physics_loss

T = lambda rows: torch.tensor(rows, dtype=torch.float64)
# theory (0,0,0),(1,0,0),(0,2,0): squared distances 1, 4, 5 -> / 5
# pred   (0,0,0),(2,0,0),(0,2,0): squared distances 4, 4, 8 -> / 8
# normalised differences: (0,1) 0.2-0.5 = -0.3, (0,2) 0.8-0.5 = 0.3, (1,2) 1-1 = 0
# L_physics = 2 * (0.09 + 0.09) / 9 = 0.04
THEORY = T([[0, 0, 0], [1, 0, 0], [0, 2, 0]])
PRED = T([[0, 0, 0], [2, 0, 0], [0, 2, 0]])
GT = T([[0, 0, 0], [1, 0, 0], [0, 2, 1]])                 # errors 0, 1, 1 -> L_data = 2/3


def test_terms_worked_example():
    assert physics_loss(PRED, THEORY).item() == pytest.approx(0.04)
    assert data_loss(PRED, GT).item() == pytest.approx(2 / 3)
    assert physics_loss(THEORY * 3.0, THEORY).item() == pytest.approx(0.0)   # scale-free (eqs. 14-15)


def test_weightings_worked_example():
    fixed = SPILoss("fixed", lambda_data=1.0, lambda_physics=2.0)
    assert fixed(PRED, GT, THEORY)[0].item() == pytest.approx(2 / 3 + 2 * 0.04)
    paper = SPILoss("paper", lambda_data=0.5, lambda_physics=4.0)
    assert paper(PRED, GT, THEORY)[0].item() == pytest.approx(0.5 * 2 / 3 + 4.0 * 0.04)
    unc = SPILoss("uncertainty", lambda_data=math.e, lambda_physics=1.0)   # s = (-1, 0)
    assert unc(PRED, GT, THEORY)[0].item() == pytest.approx(math.e * 2 / 3 + 0.04 - 1.0)
    data_only = SPILoss("fixed", physics=False)
    total, parts = data_only(PRED, GT, THEORY)
    assert total.item() == pytest.approx(2 / 3) and math.isnan(parts["physics"])


def test_paper_weights_are_trainable_and_shrink():
    paper = SPILoss("paper")
    paper(PRED, GT, THEORY)[0].backward()
    # dL/dlogλ = λ L > 0: gradient descent lowers both λ (the loose end docs/method.md names)
    assert (paper.log_lambda.grad > 0).all()
    with pytest.raises(ValueError, match="unknown 'gradnorm'"):
        SPILoss("gradnorm")
