"""The motion model: where belief over the place cells goes when the robot has moved a given distance.

No heading and no position: a frame's only motion input is the distance travelled since the previous frame
(wheel odometry, or a bound from the time elapsed × a maximum speed). The model assumes the robot is anywhere in
its cell with equal probability and moved by ``r`` metres in any direction with equal probability; the chance
of then being in the cell at row/column offset ``(o_r, o_c)`` is the overlap of the shifted cell with that cell,

    k(o_r, o_c) = E_θ,r [ tri(r cos θ / L_x − o_r) · tri(r sin θ / L_y − o_c) ],   tri(u) = max(0, 1 − |u|),

with ``L_x``, ``L_y`` the cell sides (m) and the expectation over ``n_angles`` equally spaced headings and
``n_noise`` quantiles of the distance ``r``. Exact under those two assumptions (up to the finite sums), it
depends only on the offset, so one ``(2n − 1, 2n − 1)`` kernel per frame defines every cell's transitions.
Mass that would leave the grid is given back to the cells inside (rows renormalised: the grid box holds every
viewpoint of the data, ``placejax.data.PlaceGrid.fit``).
"""

from __future__ import annotations

import statistics

import jax.numpy as jnp
import numpy as np


def distance_samples(moved_m: jnp.ndarray, noise_frac, noise_m, n_noise: int, bounded: bool) -> jnp.ndarray:
    """The distances ``r`` (m) the kernel averages over, float32 ``(n_noise,)``.

    Args:
        moved_m: scalar, distance travelled since the last frame (m).
        noise_frac, noise_m: odometry noise sd, relative (fraction of ``moved_m``) and absolute (m).
        n_noise: samples (quantiles at ``(e + 0.5) / n_noise``).
        bounded: ``moved_m`` is only an upper bound (time × maximum speed): ``r`` uniform in ``[0, moved_m]``
            instead of ``moved_m ± noise``.
    """
    q = (np.arange(n_noise) + 0.5) / n_noise
    if bounded:
        return moved_m * jnp.asarray(q, jnp.float32)
    z = jnp.asarray([statistics.NormalDist().inv_cdf(float(v)) for v in q], jnp.float32)
    sd = jnp.sqrt((noise_frac * moved_m) ** 2 + noise_m**2)
    return jnp.abs(moved_m + sd * z)


def offset_kernel(
    moved_m, cell_m: tuple, noise_frac, noise_m, *, n: int, n_angles: int, n_noise: int, bounded: bool
) -> jnp.ndarray:
    """``k(o_r, o_c)``, float32 ``(2n − 1, 2n − 1)``, index ``o + n − 1``; sums to 1 (see the module docstring).

    Args:
        moved_m: scalar distance travelled (m).
        cell_m: ``(L_x, L_y)`` cell sides (m).
        noise_frac, noise_m: odometry noise sd, relative and absolute (m).
        n: cells per grid axis.
        n_angles: headings averaged over.
        n_noise: distance samples averaged over.
        bounded: ``moved_m`` is an upper bound (see `distance_samples`).
    """
    r = distance_samples(moved_m, noise_frac, noise_m, n_noise, bounded)
    theta = 2 * np.pi * (np.arange(n_angles) + 0.5) / n_angles
    dx = (r[:, None] * jnp.asarray(np.cos(theta), jnp.float32)[None, :]).reshape(-1) / cell_m[0]
    dy = (r[:, None] * jnp.asarray(np.sin(theta), jnp.float32)[None, :]).reshape(-1) / cell_m[1]
    o = jnp.arange(-(n - 1), n, dtype=jnp.float32)
    a = jnp.maximum(0.0, 1.0 - jnp.abs(dx[:, None] - o[None, :]))  # (samples, 2n − 1) over row offsets
    b = jnp.maximum(0.0, 1.0 - jnp.abs(dy[:, None] - o[None, :]))  # over column offsets
    return (a.T @ b) / dx.shape[0]


def gather_index(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Kernel indices of every (from cell, to cell) pair: int32 ``(n², n²)`` row- and column-offset indices."""
    rc = np.stack(np.divmod(np.arange(n * n), n), axis=-1)  # (n², 2): row, col of every class id
    off = rc[None, :, :] - rc[:, None, :] + (n - 1)  # [from, to] → offset index
    return off[..., 0].astype(np.int32), off[..., 1].astype(np.int32)


def cell_transitions(kernel: jnp.ndarray, index: tuple[np.ndarray, np.ndarray]) -> jnp.ndarray:
    """Row-stochastic ``(K, K)`` transition matrix between the grid's cells (``[from, to]``) from a kernel.

    Rows whose whole mass left the grid (a distance far beyond the grid) become uniform.
    """
    m = kernel[index[0], index[1]]
    z = m.sum(axis=1, keepdims=True)
    k = m.shape[0]
    return jnp.where(z > 0, m / jnp.where(z > 0, z, 1.0), 1.0 / k)
