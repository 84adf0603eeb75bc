"""Batch kernel of the camera-side gradient estimators (DRT, sample matching, and the path
score function on backward paths, the combined gradient's backward half).

The estimators trace backward paths from pixels and deposit residual-weighted derivative
terms into per-batch gradient arrays; this module chooses the pixels and the estimator.
The pixels come either from every pixel with a non-zero residual (``per_batch``
samples of each pixel in each batch; sample k of pixel p in batch b has index
``(p * nbatch + b) * per_batch + k``, as in :func:`cloudct.mc.backward.
backward_batches`) or from an alias table in proportion to |residual|
(:mod:`cloudct.mc.pixel_sampling`; ``per_batch`` samples in all per batch, sample
k of batch b has index ``b * per_batch + k`` and draws its pixel from stream
``index`` of :data:`~cloudct.mc.random.DOMAIN_PIXEL_TABLE`). The CUDA kernel of
:mod:`cloudct.mc.cuda_kernels` uses the same indices and :func:`gradient_sample`.
"""

from __future__ import annotations

from numba import njit, prange

from cloudct.mc.accumulate import inline_on_cpu
from cloudct.mc.backward import score_pixel_sample
from cloudct.mc.drt import drt_pixel_sample
from cloudct.mc.pixel_sampling import draw_pixel
from cloudct.mc.random import DOMAIN_PIXEL_TABLE, stream_start
from cloudct.mc.sample_matching import sample_matching_pixel_sample

#: Estimator codes of the kernels, and their names in progress bars.
DRT = 0
SAMPLE_MATCHING = 1
SCORE = 2  # the path score function of backward paths (cloudct.mc.backward)
TITLES = {DRT: "DRT", SAMPLE_MATCHING: "sample matching", SCORE: "backward score function"}


@njit(cache=True, _nrt=False, inline=inline_on_cpu)
def gradient_sample(
    estimator, grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    index, view, row, col, weight, gradient, probes, quadratic, mis,
):
    """One pixel sample of ``estimator`` (:data:`DRT`, :data:`SAMPLE_MATCHING` or
    :data:`SCORE`) weighted by ``weight`` (the residual, or r_d / p_d when pixels are
    drawn); returns the path vertices traced."""
    if estimator == SCORE:
        return score_pixel_sample(
            grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
            index, view, row, col, weight, gradient,
        )
    mis_length = grid.z_edges[grid.z_edges.size - 1] - grid.z_edges[0]
    if estimator == DRT:
        return drt_pixel_sample(
            grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
            index, view, row, col, weight, gradient, mis_length,
        )
    return sample_matching_pixel_sample(
        grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index,
        view, row, col, weight, gradient, probes, quadratic, mis, mis_length,
    )


@njit(cache=True, _nrt=False)
def drawn_pixel(table, seed, index, nrows, ncols):
    """``(view, row, col, weight)`` of table-drawn sample ``index``."""
    pixel, weight, _ = draw_pixel(table, stream_start(seed, DOMAIN_PIXEL_TABLE, index))
    return pixel // (nrows * ncols), (pixel // ncols) % nrows, pixel % ncols, weight


@njit(parallel=True, cache=True, _nrt=False)
def camera_gradient_batches(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    per_batch, first, last, estimator, probes, quadratic, mis, residual, table,
    gradients, events,
):
    """gradients[b] (float64[nbatch, nx, ny, nz]) accumulates batch b's sum over its
    samples ``first .. last - 1`` of residual-weighted dI/dbeta_cloud estimates (not yet
    divided by ``per_batch``), parallel over batches; pixels as in the module
    docstring (an empty ``table``: every pixel with a non-zero residual). ``events[b]``
    accumulates the number of path vertices traced."""
    nbatch = gradients.shape[0]
    nview, nrows, ncols = residual.shape
    for b in prange(nbatch):
        n = 0
        if table.pixel.size == 0:
            for view in range(nview):
                for row in range(nrows):
                    for col in range(ncols):
                        r = residual[view, row, col]
                        if r == 0.0:
                            continue
                        pixel = (view * nrows + row) * ncols + col
                        for k in range(first, last):
                            index = (pixel * nbatch + b) * per_batch + k
                            n += gradient_sample(
                                estimator, grid, bank, cams, sun, periodic, ground_albedo,
                                rr_depth, rr_survival, seed, index, view, row, col, r,
                                gradients[b], probes, quadratic, mis,
                            )
        else:
            for k in range(first, last):
                index = b * per_batch + k
                view, row, col, weight = drawn_pixel(table, seed, index, nrows, ncols)
                n += gradient_sample(
                    estimator, grid, bank, cams, sun, periodic, ground_albedo, rr_depth,
                    rr_survival, seed, index, view, row, col, weight, gradients[b], probes,
                    quadratic, mis,
                )
        events[b] += n
