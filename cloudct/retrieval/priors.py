"""Cloud-physics priors: the terms of the retrieval's loss beside the data term.

Multi-view images do not determine a thick cloud: beyond an optical distance of about 5
from its lit and viewed boundary its interior barely shows in them (the "veiled core",
Forster et al. 2021), and many media fit the images about as well as the truth. The
retrieval therefore minimises

    L(beta) + L_empty sum_j w_j m_j Phi_j(beta)

with L the data term (seed paper Eq. 41), L_empty the data term of a medium that sends no
light to the cameras (so that a weight does not depend on the scene's brightness or pixel
count), w_j a term's weight, m_j its schedule's multiple (1, or the gradient's noise
relative to its first settled value: :func:`cloudct.retrieval.schedule.noise_weight`) and
Phi_j one of the terms below, each a discretised integral over the grid, so that neither
its value nor its weight depends on the voxel size:

- ``l1``: the cloud's extinction cross-section, Phi = int beta dV [km^2]: among media that
  fit the images about equally well, the least extinction (sparsity; AT3D's ``Sparsity``).
- ``smoothness``: Phi = sum_a c_a int rho(d beta / d x_a) dV over the three axes, with
  c_x = c_y = ``horizontal`` and c_z = ``vertical``; rho(g) = |g| (total variation) or, with
  ``huber`` = delta > 0, Huber's g^2 / (2 delta) for |g| <= delta and |g| - delta / 2 beyond
  (AT3D's ``SpatialSmoothing``; Huber 1964).
- ``monotonic``: extinction that grows with height inside a cumulus, below each column's
  level of largest extinction (Loeub et al. 2020): Phi = int max(0, -d beta / dz) dV over
  the part of each column below its maximum, so a layer of extinction under the cloud's
  base, or a hollow in its core, costs what it takes away going up.
- ``adiabatic``: each column's departure from an adiabatic profile (liquid water linear in
  height above the cloud base, the effective radius as its cube root, so extinction
  proportional to (z - z_base)^(2/3); e.g. Tzabari et al. 2022): Phi = sum over columns of
  min over a >= 0, base and top of int (beta - a f)^2 dz dA, f = (z - z_base)^(2/3) from
  the base to the top and 0 outside; the column's base, top and scale are those of the
  current medium that fit it best (each a cell edge), so the profile follows the medium.

A retrieval of liquid water content and droplet effective radius from several bands
(:mod:`cloudct.retrieval.microphysics`) takes the terms of :data:`REFF_PRIORS` instead, in
r_eff [micron] over the cells that hold droplets (r_eff > 0: the retrieval keeps r_eff 0
outside its hull), weighted in the same way:

- ``reff_smoothness``: Phi = 1/2 sum_a c_a int (d r_eff / d x_a)^2 dV over neighbouring
  cells that both hold droplets; its gradient is a discrete Laplacian of r_eff with the
  opposite sign, which pulls each r_eff towards its neighbours' mean (the images tell the
  droplets' size in the lit and viewed shell of the cloud, and the term carries it
  inwards).
- ``reff_growth``: droplets that grow with height, as they do in a cumulus (adiabatic
  ascent: r_eff as the cube root of the height above the base; e.g. Tzabari et al. 2022):
  Phi = 1/2 int max(0, -d r_eff / dz)^2 dV over vertical neighbours with droplets.

Each term's function returns ``(Phi, dPhi / d beta)`` from one call (its gradient exact
almost everywhere, tested against finite differences of its value); the records of
:data:`PRIORS` hold what each penalises, its equation's reference and its options, read
by the configuration, the command line, the report and the tests.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import xarray as xr

from cloudct.medium import cell_edges

#: How a term's weight follows the run: ``fixed``, or ``noise`` (x the gradient's rms
#: standard error over that of the stage's first iteration at settled photons).
PRIOR_SCHEDULES = ("fixed", "noise")
#: The exponent of height above the cloud base of an adiabatic cloud's extinction: LWC
#: grows linearly with height and r_eff as its cube root, beta ~ LWC / r_eff ~ h^(2/3).
ADIABATIC_EXPONENT = 2.0 / 3.0


class PriorGrid(NamedTuple):
    """The grid a prior integrates over: cell widths along x, y, z [km] (1D), the distances
    between neighbouring cell centres along each axis [km] (1D, one shorter), the cell
    centres' heights and the z edges [km], and the cell volumes [km^3] (x, y, z)."""

    widths: tuple[np.ndarray, np.ndarray, np.ndarray]
    spacings: tuple[np.ndarray, np.ndarray, np.ndarray]
    z_centres: np.ndarray
    z_edges: np.ndarray
    volume: np.ndarray

    @classmethod
    def of(cls, medium: xr.Dataset) -> PriorGrid:
        """The grid of a medium (its cell edges: CF bounds where the spacing is not
        uniform)."""
        edges = cell_edges(medium)
        widths = tuple(np.diff(e) for e in edges)
        centres = [0.5 * (e[:-1] + e[1:]) for e in edges]
        dx, dy, dz = widths
        volume = dx[:, None, None] * dy[None, :, None] * dz[None, None, :]
        return cls(widths, tuple(np.diff(c) for c in centres), centres[2], edges[2], volume)


def _along(values: np.ndarray, axis: int) -> np.ndarray:
    """A 1D array along ``axis`` of a 3D grid, shaped to broadcast."""
    shape = [1, 1, 1]
    shape[axis] = values.size
    return values.reshape(shape)


def l1(beta: np.ndarray, grid: PriorGrid) -> tuple[float, np.ndarray]:
    """The cloud's extinction cross-section int beta dV [km^2] and its gradient, the cell
    volumes."""
    return float(np.sum(beta * grid.volume)), grid.volume


def _rho(g: np.ndarray, huber: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(g) and rho'(g): |g| and sign(g), or Huber's with ``huber`` = delta > 0."""
    if huber == 0.0:
        return np.abs(g), np.sign(g)
    inner = np.abs(g) <= huber
    value = np.where(inner, 0.5 * g**2 / huber, np.abs(g) - 0.5 * huber)
    return value, np.where(inner, g / huber, np.sign(g))


def _face_area(grid: PriorGrid, axis: int) -> np.ndarray:
    """The area [km^2] of the faces between neighbouring cells along ``axis``, shaped to
    broadcast."""
    area = np.ones((1, 1, 1))
    for other in {0, 1, 2} - {axis}:
        area = area * _along(grid.widths[other], other)
    return area


def _add_pair_flux(gradient: np.ndarray, flux: np.ndarray, axis: int) -> None:
    """Add each neighbour pair's ``flux`` (the derivative of its term in the upper cell's
    value, minus that in the lower's) to ``gradient``."""
    lower = [slice(None)] * 3
    upper = [slice(None)] * 3
    lower[axis], upper[axis] = slice(None, -1), slice(1, None)
    gradient[tuple(upper)] += flux
    gradient[tuple(lower)] -= flux


def smoothness(beta: np.ndarray, grid: PriorGrid, horizontal: float = 1.0,
               vertical: float = 1.0, huber: float = 0.0) -> tuple[float, np.ndarray]:
    """sum_a c_a int rho(d beta / d x_a) dV [km] and its gradient (module docstring): each
    pair of neighbouring cells contributes c_a A rho((beta_2 - beta_1) / h) h, with h the
    distance between their centres and A the area of their common face."""
    value, gradient = 0.0, np.zeros_like(beta)
    for axis, weight in enumerate((horizontal, horizontal, vertical)):
        if weight == 0.0 or beta.shape[axis] < 2:
            continue
        h = _along(grid.spacings[axis], axis)
        area = _face_area(grid, axis)
        rho, slope = _rho(np.diff(beta, axis=axis) / h, huber)
        value += weight * float(np.sum(area * h * rho))
        # d/d beta_2 of the pair's term; -flux for beta_1
        _add_pair_flux(gradient, weight * area * slope, axis)
    return value, gradient


def monotonic(beta: np.ndarray, grid: PriorGrid) -> tuple[float, np.ndarray]:
    """int max(0, -d beta / dz) dV [km] below each column's (first) maximum and its
    gradient: each pair of vertical neighbours below the maximum contributes
    dx dy max(0, beta_k - beta_(k+1))."""
    top = np.argmax(beta, axis=2)[:, :, None]  # the level of the column's maximum
    upper = np.arange(1, beta.shape[2])[None, None, :]  # of each pair (k, k + 1)
    drop = np.maximum(beta[:, :, :-1] - beta[:, :, 1:], 0.0) * (upper <= top)
    area = grid.widths[0][:, None, None] * grid.widths[1][None, :, None]
    falling = area * (drop > 0.0)
    gradient = np.zeros_like(beta)
    gradient[:, :, :-1] += falling
    gradient[:, :, 1:] -= falling
    return float(np.sum(area * drop)), gradient


def adiabatic_fit(beta: np.ndarray, grid: PriorGrid) -> np.ndarray:
    """Each column's best adiabatic profile a (z - z_base)^(2/3), from the cell edge
    z_base up to a top cell and zero outside, least squares in int (beta - profile)^2 dz
    with a >= 0 (module docstring); float[x, y, z]. An empty column's profile is 0."""
    nz = beta.shape[2]
    dz = grid.widths[2][None, None, :]
    total = np.sum(dz * beta**2, axis=2)  # int beta^2 dz: the misfit of a = 0
    best = total.copy()
    fit = np.zeros(beta.shape[:2] + (3,))  # (a, base level, top level) of the best
    for base in range(nz):
        shape = np.maximum(grid.z_centres[base:] - grid.z_edges[base], 0.0) ** \
            ADIABATIC_EXPONENT
        cross = np.cumsum(dz[:, :, base:] * beta[:, :, base:] * shape, axis=2)
        norm = np.cumsum(grid.widths[2][base:] * shape**2)
        # the misfit of the best a >= 0 for each top: total - max(cross, 0)^2 / norm
        misfit = total[:, :, None] - np.maximum(cross, 0.0) ** 2 / norm
        top = np.argmin(misfit, axis=2)
        lowest = np.take_along_axis(misfit, top[:, :, None], axis=2)[:, :, 0]
        better = lowest < best
        best = np.where(better, lowest, best)
        scale = np.maximum(np.take_along_axis(cross, top[:, :, None], axis=2)[:, :, 0],
                           0.0) / norm[top]
        fit = np.where(better[:, :, None], np.stack(
            [scale, np.full(scale.shape, base), base + top], axis=2), fit)
    levels = np.arange(nz)[None, None, :]
    base, top = fit[:, :, 1:2], fit[:, :, 2:3]
    inside = (levels >= base) & (levels <= top)
    height = np.maximum(grid.z_centres[None, None, :] - grid.z_edges[base.astype(int)], 0.0)
    return np.where(inside, fit[:, :, 0:1] * height**ADIABATIC_EXPONENT, 0.0)


def adiabatic(beta: np.ndarray, grid: PriorGrid) -> tuple[float, np.ndarray]:
    """sum over columns of int (beta - best adiabatic profile)^2 dV [km] and its
    gradient 2 V (beta - profile): the profile's scale, base and top are at a minimum of
    the misfit, so their change with beta adds nothing (the envelope theorem)."""
    departure = beta - adiabatic_fit(beta, grid)
    return float(np.sum(grid.volume * departure**2)), 2.0 * grid.volume * departure


def _droplet_pairs(reff: np.ndarray, grid: PriorGrid, axis: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along ``axis``: each neighbour pair's difference r_2 - r_1 where both cells hold
    droplets (r_eff > 0; 0 elsewhere), the distance h between their centres and the area A
    of their common face [km], shaped to broadcast."""
    droplets = reff > 0.0
    both = np.logical_and(np.delete(droplets, -1, axis=axis), np.delete(droplets, 0, axis=axis))
    return (np.where(both, np.diff(reff, axis=axis), 0.0), _along(grid.spacings[axis], axis),
            _face_area(grid, axis))


def reff_smoothness(reff: np.ndarray, grid: PriorGrid, horizontal: float = 1.0,
                    vertical: float = 1.0) -> tuple[float, np.ndarray]:
    """1/2 sum_a c_a int (d r_eff / d x_a)^2 dV over the cloud [micron^2 km] and its
    gradient, a discrete Laplacian of r_eff with the opposite sign (module docstring):
    each pair of neighbouring cells that both hold droplets (r_eff > 0; the retrieval of
    LWC and r_eff keeps r_eff 0 outside its hull) contributes c_a A (r_2 - r_1)^2 / (2 h).
    r_eff of clear cells means nothing, so pairs with one do not count."""
    value, gradient = 0.0, np.zeros_like(reff)
    for axis, weight in enumerate((horizontal, horizontal, vertical)):
        if weight == 0.0 or reff.shape[axis] < 2:
            continue
        difference, h, area = _droplet_pairs(reff, grid, axis)
        value += weight * float(np.sum(area * difference**2 / (2.0 * h)))
        _add_pair_flux(gradient, weight * area * difference / h, axis)
    return value, gradient


def reff_growth(reff: np.ndarray, grid: PriorGrid) -> tuple[float, np.ndarray]:
    """1/2 int max(0, -d r_eff / dz)^2 dV over the cloud [micron^2 km] and its gradient:
    each vertical pair of cells that both hold droplets contributes dx dy max(0, r_k -
    r_(k+1))^2 / (2 h), so droplets that shrink going up cost the square of their fall
    (a soft penalty: in a cumulus they grow with height, module docstring)."""
    if reff.shape[2] < 2:
        return 0.0, np.zeros_like(reff)
    difference, h, area = _droplet_pairs(reff, grid, 2)
    fall = np.maximum(-difference, 0.0)
    gradient = np.zeros_like(reff)
    _add_pair_flux(gradient, -area * fall / h, 2)
    return float(np.sum(area * fall**2 / (2.0 * h))), gradient


class PriorTerm(NamedTuple):
    """A registered loss term: its name, what it penalises, its equation's source, the
    units of its weight (Phi's reciprocal), its options with their defaults, and its
    function ``(beta, grid, **options) -> (Phi, dPhi / d beta)``."""

    name: str
    penalises: str
    reference: str
    weight_units: str
    options: Mapping[str, float]
    function: Callable[..., tuple[float, np.ndarray]]


#: The loss terms by name.
PRIORS = {t.name: t for t in (
    PriorTerm("l1", "extinction (the least that fits: sparsity)",
              "AT3D regularization.Sparsity; cloudct's L1 prior since 2026-11-22",
              "km-2", {}, l1),
    PriorTerm("smoothness", "the extinction's spatial gradient: total variation, or Huber's "
              "with huber > 0 [km-2]; horizontal and vertical multiples",
              "AT3D regularization.SpatialSmoothing; Huber 1964", "km-1",
              {"horizontal": 1.0, "vertical": 1.0, "huber": 0.0}, smoothness),
    PriorTerm("monotonic", "extinction that falls with height below each column's maximum",
              "Loeub et al. 2020, monotonicity prior for cloud tomography", "km-1", {},
              monotonic),
    PriorTerm("adiabatic", "each column's departure from extinction ~ (z - z_base)^(2/3) "
              "between a fitted base and top",
              "adiabatic cloud: LWC linear in height, r_eff its cube root; Tzabari et al. 2022",
              "km-1", {}, adiabatic),
)}


#: The loss terms in the droplet effective radius of a retrieval of LWC and r_eff
#: (``unknowns = ("lwc", "reff")``, :mod:`cloudct.retrieval.microphysics`), by name; each
#: function takes r_eff [micron], 0 where there are no droplets.
REFF_PRIORS = {t.name: t for t in (
    PriorTerm("reff_smoothness", "r_eff's spatial gradient inside the cloud, squared "
              "(horizontal and vertical multiples)",
              "Tikhonov regularisation (squared first differences) of r_eff",
              "micron-2 km-1",
              {"horizontal": 1.0, "vertical": 1.0}, reff_smoothness),
    PriorTerm("reff_growth", "r_eff that falls with height inside the cloud, squared",
              "adiabatic cumulus: r_eff grows with height (e.g. Tzabari et al. 2022)",
              "micron-2 km-1", {}, reff_growth),
)}
#: Every registered term by name: :data:`PRIORS` (extinction) and :data:`REFF_PRIORS`.
TERMS = {**PRIORS, **REFF_PRIORS}


@dataclass
class Prior:
    """A term of a run's loss: the registered ``term``, its ``weight`` (in the term's
    units), its ``schedule`` (:data:`PRIOR_SCHEDULES`) and the term's ``options``
    (defaults: the record's)."""

    term: str
    weight: float
    schedule: str = "noise"
    options: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.term not in TERMS:
            raise ValueError(f"prior term must be one of {tuple(TERMS)}, got {self.term!r}")
        self.weight = float(self.weight)
        if not (np.isfinite(self.weight) and self.weight >= 0.0):
            raise ValueError(f"prior {self.term}: weight must be >= 0, got {self.weight}")
        if self.schedule not in PRIOR_SCHEDULES:
            raise ValueError(f"prior {self.term}: schedule must be one of {PRIOR_SCHEDULES}, "
                             f"got {self.schedule!r}")
        known = TERMS[self.term].options
        unknown = sorted(set(self.options) - set(known))
        if unknown:
            raise ValueError(f"prior {self.term}: unknown option {unknown[0]!r} (its options: "
                             f"{', '.join(known) or 'none'})")
        self.options = {k: float(v) for k, v in self.options.items()}
        bad = [k for k, v in self.options.items() if not (np.isfinite(v) and v >= 0.0)]
        if bad:
            raise ValueError(f"prior {self.term}: option {bad[0]} must be >= 0, got "
                             f"{self.options[bad[0]]}")

    def value_and_gradient(self, beta: np.ndarray, grid: PriorGrid) -> tuple[float, np.ndarray]:
        """The term's Phi and dPhi / d beta (unweighted) at ``beta`` (r_eff for the terms of
        :data:`REFF_PRIORS`)."""
        record = TERMS[self.term]
        return record.function(beta, grid, **{**record.options, **self.options})


def as_prior(setting: Prior | Mapping) -> Prior:
    """A :class:`Prior` from itself or from its fields (a configuration file's or result's
    dict)."""
    return setting if isinstance(setting, Prior) else Prior(**setting)


def prior_text(prior: Prior) -> str:
    """A term as ``--prior`` writes it: ``TERM=WEIGHT[,schedule=S][,OPTION=VALUE...]``."""
    parts = [f"{prior.term}={prior.weight:g}"]
    if prior.schedule != "noise":
        parts.append(f"schedule={prior.schedule}")
    parts += [f"{k}={v:g}" for k, v in prior.options.items()]
    return ",".join(parts)


def parse_prior(text: str) -> Prior:
    """``--prior``'s ``TERM=WEIGHT[,schedule=S][,OPTION=VALUE...]`` as a :class:`Prior`.

    >>> parse_prior("smoothness=0.1,vertical=0.5,schedule=fixed")
    Prior(term='smoothness', weight=0.1, schedule='fixed', options={'vertical': 0.5})
    """
    fields: dict = {"options": {}}
    for i, item in enumerate(text.split(",")):
        name, sep, value = item.partition("=")
        if not sep or not value:
            raise ValueError(f"prior {text!r}: write TERM=WEIGHT[,schedule=S][,OPTION=VALUE"
                             "...], e.g. monotonic=0.3")
        try:
            if i == 0:
                fields.update(term=name, weight=float(value))
            elif name == "schedule":
                fields["schedule"] = value
            else:
                fields["options"][name] = float(value)
        except ValueError:
            raise ValueError(f"prior {text!r}: {value!r} is not a number") from None
    return Prior(**fields)
