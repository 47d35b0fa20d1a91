"""Tests of fgslam.factors.robust: kernels vs definitions and gtsam, rho' = w e, IRLS line fit with outliers."""

import math

import gtsam
import pytest
import torch

from fgslam.core.errors import ConfigError
from fgslam.factors.robust import (
    RobustConfig,
    confidence_sqrt_information,
    irls_weights,
    kernel_cost,
    kernel_weight,
)

F64 = torch.float64
KINDS = ["huber", "cauchy", "tukey"]
GTSAM_KERNELS = {"huber": "Huber", "cauchy": "Cauchy", "tukey": "Tukey"}


@pytest.mark.parametrize("kind", KINDS)
def test_kernels_match_gtsam_mestimators(kind):
    delta = 1.7
    est = getattr(gtsam.noiseModel.mEstimator, GTSAM_KERNELS[kind]).Create(delta)
    e = torch.linspace(0, 6, 241, dtype=F64)
    w, rho = kernel_weight(e, kind, delta), kernel_cost(e, kind, delta)
    for k in range(0, 241, 7):
        assert math.isclose(w[k].item(), est.weight(e[k].item()), rel_tol=1e-12, abs_tol=1e-15)
        assert math.isclose(rho[k].item(), est.loss(e[k].item()), rel_tol=1e-12, abs_tol=1e-15)


def test_kernel_definitions():
    e = torch.tensor([0.0, 0.5, 1.0, 2.0, 4.0], dtype=F64)
    assert torch.equal(kernel_weight(e, "none", 1.0), torch.ones(5, dtype=F64))
    assert torch.allclose(kernel_cost(e, "none", 1.0), 0.5 * e**2)
    assert torch.allclose(kernel_weight(e, "huber", 1.0), torch.tensor([1, 1, 1, 0.5, 0.25], dtype=F64))
    assert torch.allclose(kernel_cost(e, "huber", 1.0), torch.tensor([0, 0.125, 0.5, 1.5, 3.5], dtype=F64))
    assert torch.allclose(kernel_weight(e, "cauchy", 2.0), 1 / (1 + e**2 / 4))
    assert torch.allclose(kernel_weight(e, "tukey", 2.0), torch.tensor([1, (1 - 1 / 16) ** 2, 0.5625, 0, 0], dtype=F64))
    with pytest.raises(ValueError):
        kernel_weight(e, "welsch", 1.0)


@pytest.mark.parametrize("kind", KINDS + ["none"])
def test_rho_derivative_equals_weight_times_e(kind):
    """rho'(e) = w(e) e by central differences (the IRLS weight is consistent with the cost)."""
    delta, h = 1.3, 1e-6
    e = torch.linspace(0.01, 5, 500, dtype=F64)
    e = e[(e - delta).abs() > 1e-4]  # the kink of Huber/Tukey's second derivative is fine, avoid only e = delta
    drho = (kernel_cost(e + h, kind, delta) - kernel_cost(e - h, kind, delta)) / (2 * h)
    assert torch.allclose(drho, kernel_weight(e, kind, delta) * e, atol=1e-7)


def test_irls_weights_confidence_and_invalid():
    cfg = RobustConfig(kind="huber", delta=1.0, min_confidence=0.5)
    r = torch.tensor(
        [[0.1, 0.0, 0.0], [3.0, 4.0, 0.0], [1.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [1.0, 1.0, 1.0]], dtype=F64
    )
    q = torch.tensor([4.0, 1.0, 0.2, 1.0, math.inf], dtype=F64)
    sigma = 0.5
    out = irls_weights(r, q, sigma, cfg)
    assert out.valid.tolist() == [True, True, False, False, False]
    # Row 0: sqrt_info = 2/0.5 = 4, e = 0.4 < 1 -> weight = 16, cost = 0.08.
    assert math.isclose(out.weight[0].item(), 16.0) and math.isclose(out.cost[0].item(), 0.5 * 0.4**2)
    # Row 1: sqrt_info = 2, e = 10 -> weight = 4 * (1/10), cost = 10 - 0.5.
    assert math.isclose(out.weight[1].item(), 0.4) and math.isclose(out.cost[1].item(), 9.5)
    assert math.isclose(out.whitened_norm[1].item(), 10.0)
    assert torch.all(out.weight[2:] == 0) and torch.all(out.cost[2:] == 0)
    assert torch.isfinite(out.weight).all() and torch.isfinite(out.cost).all()
    # Without confidences all are 1; float32 works; a batch of (2, 3) measurements.
    out32 = irls_weights(torch.randn(2, 3, 2), None, 1.0, RobustConfig(kind="cauchy", delta=2.0))
    assert out32.weight.shape == (2, 3) and out32.weight.dtype == torch.float32
    with pytest.raises(ConfigError):
        irls_weights(r, q, sigma, RobustConfig(delta=0.0))
    assert torch.equal(
        confidence_sqrt_information(torch.tensor([1.0, -1.0, 4.0]), torch.tensor([1.0, 1.0, 0.0])),
        torch.tensor([1.0, 0.0, 0.0]),
    )


def weighted_line_fit(x, y, w):
    A = torch.stack([x, torch.ones_like(x)], -1)
    return torch.linalg.solve(A.T @ (w[:, None] * A), A.T @ (w * y))


@pytest.mark.parametrize("kind,delta", [("huber", 1.345), ("cauchy", 2.3849), ("tukey", 4.6851)])
def test_irls_line_fit_with_outliers_converges_to_inlier_fit(kind, delta):
    g = torch.Generator().manual_seed(0)
    n, sigma = 200, 0.05
    x = torch.linspace(-2, 2, n, dtype=F64)
    y = 1.5 * x - 0.7 + sigma * torch.randn(n, generator=g, dtype=F64)
    outlier = torch.rand(n, generator=g, dtype=F64) < 0.25
    y = torch.where(outlier, y + 3 + 5 * torch.rand(n, generator=g, dtype=F64), y)
    conf = torch.ones(n, dtype=F64)
    inlier_fit = weighted_line_fit(x[~outlier], y[~outlier], torch.ones(int((~outlier).sum()), dtype=F64))
    ls_fit = weighted_line_fit(x, y, torch.ones(n, dtype=F64))
    assert (ls_fit - inlier_fit).abs().max() > 0.5  # plain least squares is ruined by the outliers

    cfg = RobustConfig(kind=kind, delta=delta)
    # Redescending kernels need a reasonable start: begin from the Huber fit as MASt3R-style IRLS would.
    params = ls_fit if kind == "huber" else _irls(x, y, conf, sigma, RobustConfig("huber", 1.345), ls_fit, 50)
    params = _irls(x, y, conf, sigma, cfg, params, 100)
    # Huber keeps a bounded pull of each outlier (about delta sigma): bias ~ n_out/n_in delta sigma.
    # Cauchy and Tukey downweight inliers slightly non-uniformly: within a fraction of sigma / sqrt(n).
    tol = {"huber": 0.04, "cauchy": 0.005, "tukey": 0.005}[kind]
    assert (params - inlier_fit).abs().max() < tol, (params, inlier_fit)
    if kind == "tukey":  # redescending to exactly zero: every outlier is rejected
        w = irls_weights((y - (params[0] * x + params[1]))[:, None], conf, sigma, cfg).weight
        assert torch.all(w[outlier] == 0) and torch.all(w[~outlier] > 0)
    # The IRLS iterates decrease the robust cost: the result beats the inlier fit's cost only marginally
    # and the plain LS fit's cost clearly.
    cost = lambda p: irls_weights((y - (p[0] * x + p[1]))[:, None], conf, sigma, cfg).cost.sum()
    assert cost(params) <= cost(inlier_fit) + 1e-9 and cost(params) < cost(ls_fit)


def _irls(x, y, conf, sigma, cfg, params, iters):
    for _ in range(iters):
        r = (y - (params[0] * x + params[1]))[:, None]
        params = weighted_line_fit(x, y, irls_weights(r, conf, sigma, cfg).weight)
    return params
