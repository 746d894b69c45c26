"""Two-bounce normals of a triangle mesh, differentiable with respect to its vertices.

Embree finds which triangle each camera ray meets first, and which one the refracted ray meets
next (`RayCaster.intersect_raw`, the renderer's own casts); the hit itself is then recomputed in
torch from the triangle's vertices (Moller-Trumbore: distance and barycentric coordinates), so the
smooth normals at both hits, interpolated from area-weighted vertex normals, carry gradients to
every vertex they depend on: through the barycentrics (where on the triangle the ray lands), the
refraction at the first hit (where the second lands) and the vertex normals themselves. Triangle
choices are piecewise constant and carry none. What the normals look like under an environment
map is the rendering layer's (`normals.render_layer`): the same Snell/Fresnel code as the renderer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..physics.camera import Cameras
from ..physics.optics import IOR_AIR, IOR_GLASS, interface
from .raycast import RayCaster


@dataclass
class MeshTwoBounce:
    """normal1, normal2 (V, H, W, 3) camera-frame unit smooth normals at the first and second hit
    (zero where undefined), differentiable w.r.t. the vertices; valid (V, H, W) bool: the ray enters
    at the first hit and reaches a second one from inside without total internal reflection at
    the first; view_dirs (V, H, W, 3) the world directions of the pixel-centre rays."""

    normal1: Tensor
    normal2: Tensor
    valid: Tensor
    view_dirs: Tensor


def gather_rows(values: Tensor, index: Tensor) -> Tensor:
    """values[index] for `values` (N, C) and any-shaped long `index`, with a deterministic backward
    on the CPU: index_select's backward sums with index_add_ in a fixed order, where indexing's
    (index_put_ with accumulate) sums in a varying order across threads, and the 1e-7 differences
    grew to 0.2% of a mesh's CD over the refine stage's 16 descent steps. Without this, torch's
    deterministic mode did it, at ~2 s a process for its first use (it imports torch._inductor)."""
    return torch.index_select(values, 0, index.reshape(-1)).view(*index.shape, values.shape[-1])


def vertex_normals_t(vertices: Tensor, faces: Tensor) -> Tensor:
    """(N, 3) unit area-weighted vertex normals of `vertices` (N, 3) and `faces` (F, 3) long."""
    tri = gather_rows(vertices, faces)
    fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = torch.zeros_like(vertices).index_add(0, faces.reshape(-1), fn.repeat_interleave(3, dim=0))
    return torch.nn.functional.normalize(vn, dim=-1, eps=1e-12)


def _hit(vertices: Tensor, faces: Tensor, normals: Tensor, face: Tensor, origin: Tensor, direction: Tensor):
    """Ray (origin, direction) (K, 3) against triangle `face` (K,): the hit distance (K,) and
    the interpolated unit normal (K, 3), both differentiable w.r.t. the vertices (Moller-Trumbore)."""
    tri = faces[face]
    a, b, c = gather_rows(vertices, tri).unbind(1)
    e1, e2 = b - a, c - a
    p = torch.linalg.cross(direction, e2)
    det = (e1 * p).sum(-1)
    inv = 1.0 / torch.where(det.abs() > 1e-12, det, torch.full_like(det, 1e-12))
    s = origin - a
    u = (s * p).sum(-1) * inv
    q = torch.linalg.cross(s, e1)
    v = (direction * q).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    corner = gather_rows(normals, tri)
    n = (1 - u - v)[:, None] * corner[:, 0] + u[:, None] * corner[:, 1] + v[:, None] * corner[:, 2]
    return t, torch.nn.functional.normalize(n, dim=-1, eps=1e-12)


def rays_two_bounce(vertices: Tensor, faces: Tensor, origins: Tensor, dirs: Tensor, caster: RayCaster,
                    ior: float = IOR_GLASS, ext_ior: float = IOR_AIR) -> tuple[Tensor, Tensor, Tensor]:
    """The first- and second-hit world-frame unit normals (K, 3) of rays (origins, dirs) (K, 3)
    against the mesh (zero where undefined), differentiable w.r.t. the vertices, and valid (K,)
    bool: the ray enters at the first hit and reaches a second one from inside without total
    internal reflection at the first. caster: an Embree scene of the same mesh."""
    o, d = origins, dirs
    normals = vertex_normals_t(vertices, faces)

    _, face1, _, _ = caster.intersect_raw(o.detach().cpu().numpy(), d.detach().cpu().numpy())
    i1 = torch.from_numpy(np.flatnonzero(face1 >= 0)).to(vertices.device)
    t1, n1 = _hit(vertices, faces, normals, torch.from_numpy(face1).to(vertices.device)[i1], o[i1], d[i1])
    p1 = o[i1] + t1[:, None] * d[i1]
    _, refracted, _, tir1 = interface(d[i1], n1, ext_ior / ior)
    enters = ((d[i1] * n1).sum(-1) < 0) & ~tir1

    go = torch.nonzero(enters).squeeze(-1)
    _, face2, _, _ = caster.intersect_raw(p1[go].detach().cpu().numpy(), refracted[go].detach().cpu().numpy(),
                                          offset=True)
    j2 = torch.from_numpy(np.flatnonzero(face2 >= 0)).to(vertices.device)
    k = go[j2]
    _, n2 = _hit(vertices, faces, normals, torch.from_numpy(face2).to(vertices.device)[j2], p1[k], refracted[k])

    total = len(o)
    normal1 = torch.zeros(total, 3, dtype=vertices.dtype, device=vertices.device).index_put((i1,), n1)
    normal2 = torch.zeros(total, 3, dtype=vertices.dtype, device=vertices.device).index_put((i1[k],), n2)
    valid = torch.zeros(total, dtype=torch.bool, device=vertices.device)
    valid[i1[k]] = True
    return normal1, normal2, valid


def mesh_caster(vertices: Tensor, faces: Tensor) -> RayCaster:
    """An Embree scene of the mesh (vertices (N, 3), faces (F, 3) long) as it is now."""
    return RayCaster.of(vertices.detach().cpu().numpy(), faces.cpu().numpy())


def mesh_two_bounce(vertices: Tensor, faces: Tensor, cameras: Cameras, caster: RayCaster | None = None,
                    ior: float = IOR_GLASS, ext_ior: float = IOR_AIR) -> MeshTwoBounce:
    """The first- and second-hit normals of the mesh (vertices (N, 3) float, possibly requiring
    grad; faces (F, 3) long) for the pixel-centre rays of `cameras` (same frame). caster: an
    Embree scene of the same mesh (built here when None)."""
    caster = caster or mesh_caster(vertices, faces)
    V, H, W = cameras.num_views, cameras.height, cameras.width
    cams = cameras.to(dtype=vertices.dtype, device=vertices.device)
    origins, dirs = cams.pixel_rays()
    d = dirs.reshape(-1, 3)
    normal1, normal2, valid = rays_two_bounce(vertices, faces, origins.reshape(-1, 3), d, caster, ior, ext_ior)
    shape = (V, H, W, 3)
    return MeshTwoBounce(cams.world_to_camera(normal1.view(shape)), cams.world_to_camera(normal2.view(shape)),
                         valid.view(V, H, W), d.view(shape))
