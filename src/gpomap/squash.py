"""Probit squashing of the GP's latent output into occupancy probabilities (the paper's eq. 15).

    p(x) = Phi((alpha * mu(x) + beta) / sqrt(1 + alpha^2 * v(x)))

alpha and beta are fitted as in probabilistic least-squares classification (Rasmussen & Williams,
section 6.5): by maximising the leave-one-out log predictive probability of the training labels,
whose moments are closed form from the inverse covariance:

    mu_i = y_i - [K^-1 y]_i / [K^-1]_ii,    s_i^2 = 1 / [K^-1]_ii.

Where no beam went the map uses the same probit with the latent variance scaled by kappa
(:meth:`ProbitSquash.unseen`, :func:`unseen_probit`). kappa is not fitted here: leave-one-out
moments describe interpolation, and kappa is what extrapolation needs, fitted on held-out
stretches of the log (:mod:`gpomap.extrapolation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import minimize
from scipy.special import log_ndtr, ndtr

from gpomap.config import MapConfig


def unseen_probit(num: NDArray[np.float64], den: NDArray[np.float64], variance_scale: float) -> NDArray[np.float64]:
    """The probit's argument where no beam went, from calibrated moments (any matching shapes):
    ``z = num / sqrt(1 + kappa den)``, the latent variance scaled by kappa.

    Parameters
    ----------
    num : ndarray
        ``alpha mu + beta``.
    den : ndarray
        ``alpha^2 v``, v the latent variance.
    variance_scale : float
        kappa.
    """
    return np.asarray(num) / np.sqrt(1.0 + variance_scale * np.asarray(den))


def loo_moments(K_inv: NDArray[np.float64], y: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Leave-one-out predictive mean and variance of each training target.

    Parameters
    ----------
    K_inv : ndarray of shape (n, n)
        Inverse of the noisy training covariance.
    y : ndarray of shape (n,)

    Returns
    -------
    mu, var : ndarray of shape (n,)
    """
    d = np.diag(K_inv)
    return y - (K_inv @ y) / d, 1.0 / d


def _mills(z: NDArray[np.float64]) -> NDArray[np.float64]:
    """phi(z) / Phi(z), computed in log space so it stays finite for very negative z."""
    return np.exp(-0.5 * z * z - 0.5 * np.log(2 * np.pi) - log_ndtr(z))


def loo_probit(
    y: NDArray[np.float64],
    mu: NDArray[np.float64],
    var: NDArray[np.float64],
    alpha: float,
    beta: float,
    weights: NDArray[np.float64] | None = None,
) -> tuple[float, dict[str, NDArray[np.float64] | float]]:
    """Sum of w_i log Phi(y_i (alpha mu_i + beta) / sqrt(1 + alpha^2 var_i)) and its partial derivatives.

    Parameters
    ----------
    y : ndarray of shape (n,)
        Labels, +1 or -1.
    mu, var : ndarray of shape (n,)
        Leave-one-out predictive moments.
    alpha, beta : float
    weights : ndarray of shape (n,), optional
        Weight w_i of each term (default 1; see :func:`class_weights`).

    Returns
    -------
    value : float
    grads : dict
        ``"mu"`` and ``"var"`` (ndarray of shape (n,)), ``"alpha"`` and ``"beta"`` (float).
    """
    c = 1.0 + alpha * alpha * var
    rs = 1.0 / np.sqrt(c)
    a = alpha * mu + beta
    z = y * a * rs
    w = 1.0 if weights is None else weights
    value = float(np.sum(w * log_ndtr(z)))
    g = w * _mills(z)
    return value, {
        "mu": g * y * alpha * rs,
        "var": g * (-0.5 * y * a * alpha * alpha * rs / c),
        "alpha": float(np.sum(g * (y * mu * rs - y * a * alpha * var * rs / c))),
        "beta": float(np.sum(g * y * rs)),
    }


#: Ways of weighting the leave-one-out terms: "balanced" or None (every input counts once).
CLASS_WEIGHTS = ("balanced", None)


def class_weights(y: NDArray[np.float64], class_weight: str | None = MapConfig.class_weight) -> NDArray[np.float64] | None:
    """Weights of the leave-one-out terms, ndarray of shape (n,), or None for equal weights.

    ``"balanced"`` gives each class the same total weight (n / (2 n_class) per input, as in
    scikit-learn). Free cells outnumber occupied ones several times over on real logs, and an
    unweighted objective then prefers maps that call everything free, on some logs ranking worse
    than chance (docs/choices.md, "Class weights").
    """
    if class_weight is None:
        return None
    if class_weight != "balanced":
        raise ValueError(f"class_weight must be one of {CLASS_WEIGHTS}, got {class_weight!r}")
    occupied = y > 0
    n_occ = int(occupied.sum())
    n_free = y.size - n_occ
    if n_occ == 0 or n_free == 0:
        return None
    return np.where(occupied, y.size / (2.0 * n_occ), y.size / (2.0 * n_free))


@dataclass
class ProbitSquash:
    """The calibrated probit of eq. 15.

    Parameters
    ----------
    alpha : float
        Scale of the latent mean (positive).
    beta : float
        Offset; negative values lean towards free.
    variance_scale : float
        kappa, multiplying the latent variance in :meth:`unseen` (see :mod:`gpomap.extrapolation`);
        not changed by :meth:`fit`.
    """

    alpha: float = 1.0
    beta: float = 0.0
    variance_scale: float = 1.0

    def calibrated(self, mu: NDArray[np.float64], var: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The latent moments under this squash (any matching shapes): ``alpha mu + beta`` and
        ``alpha^2 v``, what the map's squash stage takes (:class:`gpomap.stages.CalibratedMoments`)."""
        return self.alpha * np.asarray(mu) + self.beta, self.alpha**2 * np.asarray(var)

    def __call__(self, mu: NDArray[np.float64], var: NDArray[np.float64]) -> NDArray[np.float64]:
        """Occupancy probability from latent mean and variance (any matching shapes)."""
        num, den = self.calibrated(mu, var)
        return ndtr(num / np.sqrt(1.0 + den))

    def unseen(self, mu: NDArray[np.float64], var: NDArray[np.float64]) -> NDArray[np.float64]:
        """The probability where no beam went: the latent variance scaled by kappa (a tiled map
        also cuts its lean towards free, :meth:`gpomap.tiles.TiledGPOM.squash_moments`)."""
        return ndtr(unseen_probit(*self.calibrated(mu, var), self.variance_scale))

    def fit(
        self,
        y: NDArray[np.float64],
        loo_mu: NDArray[np.float64],
        loo_var: NDArray[np.float64],
        weights: NDArray[np.float64] | None = None,
    ) -> ProbitSquash:
        """Fit alpha and beta by maximising the (weighted) leave-one-out log predictive probability (kappa = 1).

        Parameters
        ----------
        y : ndarray of shape (n,)
            Training labels, +1 occupied and -1 free.
        loo_mu, loo_var : ndarray of shape (n,)
            Leave-one-out moments (see :func:`loo_moments`).
        weights : ndarray of shape (n,), optional
            Weight of each input's term (see :func:`class_weights`).

        Returns
        -------
        self
        """

        def neg(params: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
            alpha, shift = float(np.exp(params[0])), float(params[1])
            v, g = loo_probit(y, loo_mu, loo_var, alpha, alpha * shift, weights)
            return -v, -np.array(probit_gradient_in_shift(g, alpha, shift))

        x0 = np.array([np.log(max(self.alpha, 1e-3)), self.beta / max(self.alpha, 1e-3)])
        res = minimize(neg, x0, jac=True, method="L-BFGS-B", bounds=list(SQUASH_BOUNDS))
        self.alpha = float(np.exp(res.x[0]))
        self.beta = self.alpha * float(res.x[1])
        return self


#: Search bounds of (log alpha, beta / alpha). The shift beta / alpha is the latent value where
#: the map turns from free to occupied; searching over it keeps the problem well scaled. alpha is
#: capped at 30: where the leave-one-out predictions separate the classes, the objective rises
#: with alpha for ever (the map then turns hard 0 / 1 with no unknown band), while well-posed data
#: settles far below the cap. The shift is held at 0: the GP's prior mean is 0, so with beta = 0
#: the map far from every observation is exactly p = 0.5 ("unknown"), as an occupancy map must
#: be; learnt, beta made unobserved space lean occupied, and the classes are balanced by weights
#: instead (docs/choices.md, "The map is the GP as the prior of a fine grid"; "Measured for the
#: code").
SQUASH_BOUNDS: tuple[tuple[float, float], tuple[float, float]] = ((np.log(1e-3), np.log(30.0)), (0.0, 0.0))


def probit_gradient_in_shift(g: dict, alpha: float, shift: float) -> tuple[float, float]:
    """Gradient of :func:`loo_probit` with respect to (log alpha, shift), where beta = alpha * shift.

    Parameters
    ----------
    g : dict
        The partial derivatives :func:`loo_probit` returns.
    alpha, shift : float
    """
    return alpha * (g["alpha"] + g["beta"] * shift), g["beta"] * alpha
