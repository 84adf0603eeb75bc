"""A retrieval run's fingerprint (:func:`run_id`): the measurements and the settings that
change its iterates, so that a checkpoint resumes only its own run, also one written before
a setting was added."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict

import numpy as np
import xarray as xr

from cloudct.retrieval.config import AUTO, RetrievalConfig
from cloudct.retrieval.priors import Prior


def run_id(measurements: xr.Dataset, config: RetrievalConfig) -> str:
    """A fingerprint of the measurements and settings: a checkpoint resumes only its run."""
    h = hashlib.sha256(np.ascontiguousarray(measurements["radiance"].values).tobytes())
    # the path stores' memory picks how they are stored, which changes rounding only; the
    # iterate average does not change the iterates
    ignored = ["iterations", "time_limit", "recycling_memory", "averaging", "averaging_decay"]
    # settings added later are fingerprinted only where they act (old checkpoints resume)
    if config.optimizer != "lbfgsb":
        ignored.append("trust_region")
    ignored.append("priors")  # fingerprinted below, as the L1 prior was before the others
    if config.recycle_gradient:
        ignored.append("recycle_gradient")
    if all(name == "score" for name in config.estimator):
        ignored.append("estimator")
    if config.pixel_sampling == "uniform":
        ignored.append("pixel_sampling")
    if config.transmittance == "exponential":
        ignored.append("transmittance")
    if config.photons != AUTO:
        ignored.append("iteration_seconds")
    if config.schedule == "threshold":  # the schedule before the noise test
        ignored.append("schedule")
    if config.schedule != "noise":
        ignored.append("significance")
    if config.plateau == "step":
        ignored += ["plateau", "photon_growth", "photon_cap"]
    if not config.microphysical:
        ignored += ["unknowns", "lwc_step", "reff_step", "extinction_share",
                    "hold_extinction"]
    for name, before in (("step_floor", 0.0), ("max_change", None),
                         ("image_method", "forward")):
        if getattr(config, name) == before:
            ignored.append(name)
    settings = {k: v for k, v in asdict(config).items() if k not in ignored}
    settings.update(prior_fingerprint(config.priors))
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()[:16]


def prior_fingerprint(priors: tuple[Prior, ...]) -> dict:
    """The priors' part of :func:`run_id`: none for no prior and the settings ``sparsity``
    (and ``sparsity_schedule`` unless fixed) for the L1 term alone without options, as
    runs fingerprinted them before the other terms (so their checkpoints resume); else the
    terms themselves."""
    priors = tuple(p for p in priors if p.weight > 0.0)
    if not priors:
        return {}
    if len(priors) == 1 and priors[0].term == "l1" and not priors[0].options:
        legacy = {"sparsity": priors[0].weight}
        if priors[0].schedule != "fixed":
            legacy["sparsity_schedule"] = priors[0].schedule
        return legacy
    return {"priors": [asdict(p) for p in priors]}
