"""Retrieval quality, seed paper Eq. (54), over the cloud extinction grid:

    epsilon = ||b* - b||_1 / ||b*||_1,   delta = (||b*||_1 - ||b||_1) / ||b*||_1.

A retrieval of liquid water content and droplet effective radius
(:mod:`cloudct.retrieval.microphysics`) reports epsilon and delta of the LWC field and
:func:`reff_absolute_error` and :func:`reff_relative_error` over the true cloud.

:func:`epsilon_split` tells where epsilon comes from: extinction retrieved where the true
cloud has none (e.g. the empty part of a space-carved hull) and errors inside the cloud.
:func:`epsilon_by_shell` splits the errors inside the cloud further, by the voxels' optical
distance from the cloud's lit and viewed boundary (:mod:`cloudct.mc.visibility`): where the
images constrain the cloud (below 2) and its veiled core (beyond 5), where a prior speaks.
"""

from __future__ import annotations

import numpy as np


def _fields(truth: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    truth = np.asarray(truth, dtype=float)
    estimate = np.asarray(estimate, dtype=float)
    if truth.shape != estimate.shape:
        raise ValueError(f"grids differ: truth {truth.shape}, estimate {estimate.shape}")
    norm = np.abs(truth).sum()
    if norm == 0:
        raise ValueError("the true extinction is zero everywhere: epsilon is undefined")
    return truth, estimate, float(norm)


def epsilon_delta(truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """(epsilon, delta) of an estimated extinction field against the true one.

    A retrieval that put 12 and 15 /km where the truth holds 10 and 20 /km is off by 7 of
    the true 30 /km, and holds a tenth too little:

    >>> import numpy as np
    >>> epsilon_delta(np.array([0.0, 10.0, 20.0]), np.array([0.0, 12.0, 15.0]))
    (0.23333333333333334, 0.1)
    """
    truth, estimate, norm = _fields(truth, estimate)
    return (
        float(np.abs(truth - estimate).sum() / norm),
        float((norm - np.abs(estimate).sum()) / norm),
    )


def epsilon_split(truth: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """Epsilon as the sum of its parts, each relative to ||b*||_1:

    - ``outside``: ||b||_1 over the voxels where the truth is zero (extinction put where
      there is no cloud);
    - ``inside``: ||b* - b||_1 over the cloud's voxels;
    - ``cloud_mass``: ||b||_1 over the cloud's voxels (1: the cloud holds the true mass).

    ``outside + inside`` is epsilon.
    """
    truth, estimate, norm = _fields(truth, estimate)
    cloud = truth != 0
    return {
        "outside": float(np.abs(estimate[~cloud]).sum() / norm),
        "inside": float(np.abs(truth - estimate)[cloud].sum() / norm),
        "cloud_mass": float(np.abs(estimate[cloud]).sum() / norm),
    }


#: Edges of the optical-distance shells of :func:`epsilon_by_shell`: the distance d from
#: the lit and viewed boundary (:func:`cloudct.mc.visibility.boundary_optical_distance`)
#: below 2, from 2 to 5, beyond 5 (the "veiled core", Forster et al. 2021).
SHELLS = (2.0, 5.0)


def shell_names(edges: tuple[float, ...] = SHELLS) -> list[str]:
    """The shells' keys for increasing ``edges``: ``"below 2"``, ``"2 to 5"``,
    ``"beyond 5"`` for the default (edges written with ``:g``).

    >>> shell_names((1.0, 2.5, 10.0))
    ['below 1', '1 to 2.5', '2.5 to 10', 'beyond 10']
    """
    edges = _edges(edges)
    return ([f"below {edges[0]:g}"]
            + [f"{a:g} to {b:g}" for a, b in zip(edges[:-1], edges[1:], strict=True)]
            + [f"beyond {edges[-1]:g}"])


def _edges(edges) -> tuple[float, ...]:
    edges = tuple(float(e) for e in edges)
    if not edges or any(not np.isfinite(e) for e in edges) or any(
            b <= a for a, b in zip(edges[:-1], edges[1:], strict=True)):
        raise ValueError(f"shell edges must be finite and increasing, got {edges}")
    return edges


def shell_index(distance: np.ndarray, edges: tuple[float, ...] = SHELLS) -> np.ndarray:
    """Each voxel's shell, int64 of ``distance``'s shape: 0 where d < edges[0], i where
    edges[i - 1] <= d < edges[i], len(edges) where d >= edges[-1] (the order of
    :func:`shell_names`).

    >>> shell_index(np.array([0.5, 2.0, 4.9, 5.0, 30.0])).tolist()
    [0, 1, 1, 2, 2]
    """
    return np.digitize(np.asarray(distance, dtype=float), _edges(edges)).astype(np.int64)


def epsilon_by_shell(
    truth: np.ndarray, estimate: np.ndarray, distance: np.ndarray,
    edges: tuple[float, ...] = SHELLS,
) -> dict[str, float]:
    """Epsilon split by where the error lives: outside the true cloud, and in shells of the
    true cloud's voxels by ``distance`` (their optical distance from the lit and viewed
    boundary, :func:`cloudct.mc.visibility.boundary_optical_distance`; shells of
    :func:`shell_index`). Keys, every value relative to ||b*||_1 but the ratios:

    - ``"outside"``: ||b||_1 where the truth is zero (as in :func:`epsilon_split`);
    - per shell S of :func:`shell_names` (``"below 2"``, ``"2 to 5"``, ``"beyond 5"``):
      ``S``: ||b* - b||_1 over the true cloud's voxels in S (its part of epsilon);
      ``S + ": true mass"``: ||b*||_1 in S (the shares sum to 1);
      ``S + ": retrieved/true"``: ||b||_1 / ||b*||_1 in S (NaN where S holds no cloud).

    ``outside`` plus the shells' parts is epsilon. Truth 0, 10, 20, 10 /km at distances
    0, 1, 3 and 7, retrieved as 1, 12, 15, 10 /km: epsilon 8 / 40, of which 1 / 40 outside,
    2 / 40 below 2 and 5 / 40 from 2 to 5:

    >>> parts = epsilon_by_shell(np.array([0.0, 10.0, 20.0, 10.0]),
    ...                          np.array([1.0, 12.0, 15.0, 10.0]), np.array([0.0, 1, 3, 7]))
    >>> {key: round(value, 3) for key, value in parts.items()}  # doctest: +NORMALIZE_WHITESPACE
    {'outside': 0.025, 'below 2': 0.05, 'below 2: true mass': 0.25,
     'below 2: retrieved/true': 1.2, '2 to 5': 0.125, '2 to 5: true mass': 0.5,
     '2 to 5: retrieved/true': 0.75, 'beyond 5': 0.0, 'beyond 5: true mass': 0.25,
     'beyond 5: retrieved/true': 1.0}
    >>> round(parts["outside"] + sum(parts[s] for s in shell_names()), 12)
    0.2
    """
    truth, estimate, norm = _fields(truth, estimate)
    distance = np.asarray(distance, dtype=float)
    if distance.shape != truth.shape:
        raise ValueError(f"grids differ: truth {truth.shape}, distance {distance.shape}")
    cloud = truth != 0
    shell = shell_index(distance, edges)
    parts = {"outside": float(np.abs(estimate[~cloud]).sum() / norm)}
    for i, name in enumerate(shell_names(edges)):
        inside = cloud & (shell == i)
        true_mass = float(np.abs(truth[inside]).sum())
        parts[name] = float(np.abs(truth - estimate)[inside].sum() / norm)
        parts[f"{name}: true mass"] = true_mass / norm
        parts[f"{name}: retrieved/true"] = (float(np.abs(estimate[inside]).sum()) / true_mass
                                            if true_mass > 0 else float("nan"))
    return parts


def _droplet_voxels(truth_lwc: np.ndarray, truth_reff: np.ndarray, reff: np.ndarray,
                    within: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The true and estimated r_eff of the true cloud's voxels (truth LWC > 0), and of those
    only where ``within`` (booleans) is true, when given."""
    truth_lwc, truth_reff, reff = (np.asarray(a, dtype=float)
                                   for a in (truth_lwc, truth_reff, reff))
    if not truth_lwc.shape == truth_reff.shape == reff.shape:
        raise ValueError(f"grids differ: truth {truth_lwc.shape} and {truth_reff.shape}, "
                         f"estimate {reff.shape}")
    cloud = truth_lwc > 0.0
    if not cloud.any():
        raise ValueError("the true LWC is zero everywhere: r_eff errors are undefined")
    if within is not None:
        cloud &= np.asarray(within, dtype=bool)
    return truth_reff[cloud], reff[cloud]


def reff_absolute_error(truth_lwc: np.ndarray, truth_reff: np.ndarray, reff: np.ndarray,
                        within: np.ndarray | None = None) -> float:
    """The mean absolute error of the effective radius [micron], mean |r* - r| over the true
    cloud's voxels (truth LWC > 0; only those where ``within``, e.g. optical distance from
    the boundary below 5, when given; NaN where none is). A voxel retrieved clear still
    counts with its r_eff.

    Truth 10 and 14 micron in two cloudy voxels (the third clear), retrieved as 11 and 11:

    >>> reff_absolute_error(np.array([0.0, 0.3, 0.5]), np.array([0.0, 10.0, 14.0]),
    ...                     np.array([0.0, 11.0, 11.0]))
    2.0
    """
    true, estimate = _droplet_voxels(truth_lwc, truth_reff, reff, within)
    return float(np.mean(np.abs(true - estimate))) if true.size else float("nan")


def reff_relative_error(truth_lwc: np.ndarray, truth_reff: np.ndarray, reff: np.ndarray,
                        within: np.ndarray | None = None) -> float:
    """The mean relative error of the effective radius, mean |r* - r| / r* over the true
    cloud's voxels (as :func:`reff_absolute_error`).

    >>> reff_relative_error(np.array([0.0, 0.3, 0.5]), np.array([0.0, 10.0, 14.0]),
    ...                     np.array([0.0, 11.0, 11.0]), within=np.array([True, True, False]))
    0.1
    """
    true, estimate = _droplet_voxels(truth_lwc, truth_reff, reff, within)
    return float(np.mean(np.abs(true - estimate) / true)) if true.size else float("nan")
