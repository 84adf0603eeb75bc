"""A retrieval's state: what changes during a run, its per-iteration log, and how both
travel through a result or checkpoint file (written by
:meth:`cloudct.retrieval.loop.Retrieval.result`, read back by ``Retrieval.resume``)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import xarray as xr

#: The parts of epsilon the log keeps (``epsilon_`` + the key, spaces as underscores):
#: outside the true cloud and in each optical-distance shell of
#: :func:`cloudct.retrieval.metrics.epsilon_by_shell`.
SHELL_PARTS = ("outside", "below 2", "2 to 5", "beyond 5")
#: The columns of the per-iteration log (``log_*`` variables over ``iteration``).
LOG_FIELDS = ("loss", "loss_std_error", "epsilon", "delta", "seconds", "photons", "step",
              "stage", "resampled", "ess", "gradient_seconds", "epsilon_average",
              "delta_average", "prior", "compile_seconds",
              *(f"epsilon_{part.replace(' ', '_')}" for part in SHELL_PARTS))
#: Units and long names of the log's columns (the others are counts and fractions).
LOG_ATTRS = {
    "loss": ("1", "loss, seed paper Eq. (41)"),
    "loss_std_error": ("1", "Monte Carlo standard error of the loss (from the images' "
                            "batches; NaN where not known)"),
    "epsilon": ("1", "epsilon, seed paper Eq. (54)"),
    "delta": ("1", "delta, seed paper Eq. (54)"),
    "seconds": ("s", "cumulative wall time"),
    "photons": ("1", "photons of the iteration: the residual's images' and the gradient's"),
    "step": ("km-1", "the optimiser's step of the iteration (stage multiple and decays in)"),
    "gradient_seconds": ("s", "wall time of the iteration's fresh gradient (NaN: replayed)"),
    "compile_seconds": ("s", "wall time of the iteration spent compiling kernels or loading "
                             "them from the cache (cloudct.jit_cache.compile_clock)"),
    "epsilon_average": ("1", "epsilon of the iterate average"),
    "delta_average": ("1", "delta of the iterate average"),
    **{f"epsilon_{part.replace(' ', '_')}": (
        "1", f"epsilon's part {part} the true cloud" if part == "outside" else
        f"epsilon's part in the true cloud's voxels at optical distances {part} from its lit "
        "and viewed boundary") for part in SHELL_PARTS},
    "prior": ("1", "the priors' part of the loss at the iterate the step started from "
                   "(cloudct.retrieval.priors; NaN with lbfgsb)"),
}


@dataclass(kw_only=True)
class ScheduleState:
    """What the step and photon schedule (:func:`cloudct.retrieval.schedule.advance`) reads
    and changes during a run, of the extinction's retrieval and of LWC and r_eff's alike;
    ``log`` holds at least the columns ``loss`` and ``loss_std_error``."""

    iteration: int = 0
    stage: int = 0
    log: dict[str, list[float]] = field(
        default_factory=lambda: {"loss": [], "loss_std_error": []})
    elapsed: float = 0.0
    step_scale: float = 1.0  # the step is the configured step x this (step decay)
    decayed_at: int = 0  # iteration of the schedule's last change (its window restarts)
    photons: int = 0  # gradient paths per iteration at the finest stage, now
    photons_settled: bool = True  # photons "auto": the count fits the device
    photons_base: int = 0  # the count the run settled at (photon_cap's unit)
    decays: int = 0  # step decays so far
    at_floor: bool = False  # the photons at their cap and the step at its floor
    decisions: list[dict] = field(default_factory=list)  # what the run changed, and why

    def attrs(self) -> dict:
        """The schedule's scalars as netCDF attributes."""
        return dict(
            iterations_done=self.iteration, stage=self.stage, elapsed_s=self.elapsed,
            step_scale=self.step_scale, decayed_at=self.decayed_at, photons_now=self.photons,
            photons_settled=int(self.photons_settled), photons_base=self.photons_base,
            decays=self.decays, at_floor=int(self.at_floor),
            decisions=json.dumps(self.decisions),
        )


@dataclass(kw_only=True)
class RetrievalState(ScheduleState):
    """Everything that changes during a retrieval of the extinction."""

    extinction: np.ndarray
    optimizer_state: dict[str, np.ndarray]
    log: dict[str, list[float]] = field(default_factory=lambda: {k: [] for k in LOG_FIELDS})
    average_sum: np.ndarray | None = None  # weighted sum of the iterates since the restart
    average_weight: float = 0.0  # its sum of weights (Retrieval.average)
    noise_reference: float = 0.0  # sparsity_schedule "noise": the gradient rms of the stage's first
    # iteration at the settled photon count

    def attrs(self) -> dict:
        """The state's scalars as netCDF attributes (:func:`state_from_file` reads them)."""
        return {**super().attrs(), "average_weight": self.average_weight,
                "noise_reference": self.noise_reference}

    def add_log_to(self, ds: xr.Dataset) -> xr.Dataset:
        """``ds`` with the log as ``log_*`` variables over ``iteration``."""
        ds = ds.assign_coords(iteration=np.arange(1, len(self.log["loss"]) + 1))
        for key in LOG_FIELDS:
            ds[f"log_{key}"] = ("iteration", np.array(self.log[key], dtype=float))
            if key in LOG_ATTRS:
                units, name = LOG_ATTRS[key]
                ds[f"log_{key}"].attrs.update(units=units, long_name=name)
        return ds


def state_from_file(ck: xr.Dataset, new: RetrievalState) -> RetrievalState:
    """The state stored in checkpoint ``ck``; what an older checkpoint lacks is taken from
    ``new`` (the state a new run with the same settings starts in), and log columns added
    later are NaN."""
    n = ck.sizes["iteration"]
    log = {k: [float(v) for v in (ck[f"log_{k}"].values if f"log_{k}" in ck
                                  else np.full(n, np.nan))] for k in LOG_FIELDS}
    optimizer_state = {
        name.removeprefix("optimizer_"): ck[name].values
        for name in ck.data_vars if name.startswith("optimizer_")
    }
    a = ck.attrs
    return RetrievalState(
        iteration=int(a["iterations_done"]), stage=int(a["stage"]),
        extinction=ck["cloud_extinction"].values.astype(float),
        optimizer_state=optimizer_state, log=log, elapsed=float(a["elapsed_s"]),
        step_scale=float(a["step_scale"]), decayed_at=int(a["decayed_at"]),
        average_sum=ck["average_sum"].values if "average_sum" in ck else None,
        average_weight=float(a.get("average_weight", 0.0)),
        photons=int(a.get("photons_now", new.photons)),
        photons_settled=bool(a.get("photons_settled", new.photons_settled)),
        photons_base=int(a.get("photons_base", new.photons_base)),
        decays=int(a.get("decays", 0)), at_floor=bool(a.get("at_floor", 0)),
        noise_reference=float(a.get("noise_reference", 0.0)),
        decisions=json.loads(a.get("decisions", "[]")),
    )
