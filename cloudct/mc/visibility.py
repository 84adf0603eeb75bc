"""How deep each voxel lies inside the cloud, as the sun and the cameras see it.

Multi-view images of a thick cloud speak about its lit and viewed skin and barely about
its interior beyond an optical distance of about 5 from that skin, the "veiled core"
(Forster et al. 2021): light that reaches a camera from deeper has been scattered many
times and carries little of where it was. :func:`boundary_optical_distance` measures, for
every voxel centre, that distance for the scene at hand:

    d = tau_sun + min over the cameras of tau_camera,

with tau_sun the optical depth of the cloud from the voxel centre towards the sun (along
minus the sunlight's direction of travel) until the ray leaves the medium, and tau_camera
the optical depth from the voxel centre towards a camera until the ray leaves the medium:
towards its position for a pinhole, along minus its viewing direction for an orthographic
camera. It is the optical path of the shortest single-scattering route sun -> voxel ->
camera, the cloud's own extinction only: the optical depths are those of the medium's
``cloud_extinction`` as it is stored (no air, no delta-scaling of a phase truncation, the
plain integral of extinction along the ray even under a non-exponential transmittance).
Boundaries are those of the scene: ``open`` rays end on any face of the box, ``periodic``
rays wrap across the side faces until they leave through the top or the bottom
(:func:`cloudct.mc.traversal.march`).

Retrieval reports split epsilon by this distance
(:func:`cloudct.retrieval.metrics.epsilon_by_shell`): below 2, the part of the cloud the
images constrain; beyond 5, the part a prior fills.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from numba import njit

from cloudct.mc.scene import Scene
from cloudct.mc.traversal import INF, locate_point, march
from cloudct.medium import cell_edges
from cloudct.physics.mixing import OpticalGrid
from cloudct.physics.transmittance import EXPONENTIAL


def cloud_grid(medium: xr.Dataset) -> OpticalGrid:
    """The kernels' grid of the medium's cloud extinction alone: one particle type holding
    ``cloud_extinction`` [1/km] as stored (no air, no phase-truncation scaling), the
    exponential transmittance; albedos and phase indices are zero (unused by the walks)."""
    if "cloud_extinction" not in medium:
        raise ValueError("boundary optical distances need the medium's cloud_extinction: "
                         "convert a microphysical medium with cloudct.optics.to_optical")
    x_edges, y_edges, z_edges = cell_edges(medium)
    beta = np.asarray(medium["cloud_extinction"].transpose("x", "y", "z").values, np.float64)
    if not np.all(np.isfinite(beta) & (beta >= 0.0)):
        raise ValueError("cloud_extinction must be finite and non-negative")
    shape = (1, *beta.shape)
    return OpticalGrid(
        x_edges=np.ascontiguousarray(x_edges, dtype=np.float64),
        y_edges=np.ascontiguousarray(y_edges, dtype=np.float64),
        z_edges=np.ascontiguousarray(z_edges, dtype=np.float64),
        extinction=np.ascontiguousarray(beta.reshape(shape)),
        albedo=np.zeros(shape),
        phase_index=np.zeros(shape, dtype=np.int32),
        phase_weight=np.zeros(shape),
        cloud_reff_slopes=np.zeros((2, 1, 1, 1)),
        transmittance_family=np.array([EXPONENTIAL], dtype=np.int64),
        transmittance_mode=np.zeros((1, 1, 1)),
    )


@njit(cache=True)
def voxel_optical_depths(
    grid: OpticalGrid, targets: np.ndarray, is_point: np.ndarray, periodic: bool
) -> np.ndarray:
    """Optical depth from every voxel centre (the midpoint of its cell edges) towards each
    target, until the ray leaves the medium.

    ``targets`` is float64[ntarget, 3]: where ``is_point[t]`` (bool), a point [km] (the ray
    runs from the centre towards it and also ends there: the optical depth between the two
    points, which for a point outside the medium is that to where the ray leaves it);
    otherwise a direction (need not be unit; with periodic boundaries it must not be
    horizontal). ``periodic`` as in :func:`cloudct.mc.traversal.march`. Returns
    float64[ntarget, nx, ny, nz]; a voxel centre on a point target gets 0.
    """
    xe = grid.x_edges
    ye = grid.y_edges
    ze = grid.z_edges
    nx = xe.size - 1
    ny = ye.size - 1
    nz = ze.size - 1
    depth = np.zeros((targets.shape[0], nx, ny, nz))
    for t in range(targets.shape[0]):
        for i in range(nx):
            px = 0.5 * (xe[i] + xe[i + 1])
            for j in range(ny):
                py = 0.5 * (ye[j] + ye[j + 1])
                for k in range(nz):
                    pz = 0.5 * (ze[k] + ze[k + 1])
                    ux = targets[t, 0]
                    uy = targets[t, 1]
                    uz = targets[t, 2]
                    if is_point[t]:
                        ux -= px
                        uy -= py
                        uz -= pz
                    norm = np.sqrt(ux * ux + uy * uy + uz * uz)
                    if norm == 0.0:
                        continue
                    ux /= norm
                    uy /= norm
                    uz /= norm
                    reach = norm if is_point[t] else INF
                    ix, iy, iz = locate_point(grid, px, py, pz, ux, uy, uz)
                    depth[t, i, j, k] = march(grid, px, py, pz, ux, uy, uz, ix, iy, iz, INF,
                                              periodic, None, 0.0, reach, None)[7]
    return depth


def sun_and_camera_depths(medium: xr.Dataset, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """The cloud's optical depths from every voxel centre towards the sun,
    float64[x, y, z], and towards each of the scene's cameras, float64[view, x, y, z]
    (module documentation)."""
    targets = [-np.asarray(scene.sun.travel_direction(), dtype=np.float64)]
    is_point = [False]
    for camera in scene.cameras:
        if camera.projection == "pinhole":
            targets.append(np.asarray(camera.position, dtype=np.float64))
            is_point.append(True)
        else:  # parallel rays: towards the camera is minus its viewing direction
            targets.append(-camera.frame()[0])
            is_point.append(False)
    targets = np.ascontiguousarray(targets, dtype=np.float64)
    is_point = np.array(is_point, dtype=np.bool_)
    if scene.periodic and np.any(~is_point & (targets[:, 2] == 0.0)):
        raise ValueError("a horizontal direction never leaves a periodic medium")
    depth = voxel_optical_depths(cloud_grid(medium), targets, is_point, scene.periodic)
    return depth[0], depth[1:]


def boundary_optical_distance(medium: xr.Dataset, scene: Scene) -> np.ndarray:
    """For every voxel centre, the cloud's optical depth towards the sun plus the smallest
    of its optical depths towards the scene's cameras, float64[x, y, z]: how far, optically,
    the voxel lies from the cloud's lit and viewed boundary (module documentation). Only
    ``cloud_extinction`` counts, not the air (:func:`cloud_grid`)."""
    sun, cameras = sun_and_camera_depths(medium, scene)
    return sun + cameras.min(axis=0)
