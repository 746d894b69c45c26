"""Rendering smooth glass meshes under a distant environment map, and their two-bounce maps.

Two entry points, one physics:

* `trace_two_bounce(mesh, cameras, ior, ext_ior)`: per pixel centre, the first hit and, after
  refraction, the second hit of the camera ray: normals (camera frame), points (world), depths,
  the total-internal-reflection mask and a validity mask. This is what the visual hull's
  Ñ1/Ñ2 and the ground truth N̂1/N̂2 are.
* `render_views(mesh, envmap, cameras, config)`: the full image (light transport through the
  smooth dielectric, reflection and refraction at every interface, Fresnel-weighted, total
  internal reflection, up to `max_depth` interfaces, anti-aliased) plus the two-bounce maps above
  (computed by `trace_two_bounce`'s own code, on the same Embree scene); with `region`, the mesh
  traced only where the image is read (a comparison with photos).

Light transport: a wavefront of rays over all views, deterministic Fresnel branching (both the
reflected and the refracted branch are followed, weighted F and 1 - F), pruning of branches under
a throughput threshold with a "rest" term, no absorption. Its only noise is anti-aliasing, so it
converges far faster per sample than a path tracer that picks one branch at random; it agrees
with Mitsuba 3's `path` integrator to Mitsuba's own noise floor (tests/test_render.py).

Frames and conventions (DESIGN.md): world is y-up; rays come from `Cameras.pixel_rays` /
`Cameras.directions_at`; normals returned to callers are in the camera frame x = right, y = up,
z = -forward (`Cameras.world_to_camera`); environment lookups are `EnvironmentMap.lookup` (Mitsuba's
convention); interfaces are `physics.optics.interface`; ray casting is Embree through `RayCaster`.

Shading uses the mesh's smooth (vertex-interpolated, area-weighted trimesh) normals, exactly as
Mitsuba 3 does with a PLY that carries those normals. Like Mitsuba's `dielectric` BSDF, the side a
ray arrives from (outside = air, inside = glass) is decided by the sign of dot(d, smooth normal),
so the mesh must be closed and consistently oriented with outward normals.

Radiance: a dielectric's Fresnel weights are colourless, so each path carries a scalar
throughput; radiance crossing into glass is scaled by 1/eta^2 and back by eta^2, which cancels on
every path that can reach the (outside) environment, so no such factor appears.
"""

from __future__ import annotations

import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh
from torch import Tensor

from ..physics.camera import Cameras
from ..physics.environment import EnvironmentMap
from ..physics.optics import IOR_AIR, IOR_GLASS, interface
from ..threads import torch_threads
from .raycast import RayCaster


# ---------------------------------------------------------------------------------------------
# configuration and results
# ---------------------------------------------------------------------------------------------
@dataclass
class RenderConfig:
    """Settings of `render_views`.

    ior, ext_ior: refractive indices of the glass and of the surrounding medium.
    max_depth: most interfaces (reflections + refractions) on a path; a path still inside the
        scene after that many is dropped. Equals Mitsuba's `path` integrator `max_depth - 1`.
    samples_per_axis: s; each pixel is sampled on an s x s stratified grid (spp = s^2), a box
        filter like Mitsuba's `box` rfilter.
    jitter: jitter each sample uniformly inside its stratum (seeded by `seed`; converges to the
        box-filtered pixel) instead of taking the stratum centres.
    prune_threshold: branches whose throughput (per sample, starting at 1) falls below this are
        ended. Their throughput is kept as a "rest" term times the environment's mean radiance
        when `prune_rest` (exact for a constant environment; the residual bias is measured in
        tests/test_render.py and docs/benchmarks_render.md).
    device: torch device for the shading arithmetic (Embree itself always runs on the CPU).
    chunk_rays: most live branches in one worker's wavefront (bounds memory: ~200 bytes each).
    threads: worker threads (None: all CPUs); each runs its own wavefront.
    """

    ior: float = IOR_GLASS
    ext_ior: float = IOR_AIR
    max_depth: int = 64
    samples_per_axis: int = 2
    jitter: bool = True
    seed: int = 0
    prune_threshold: float = 1e-3
    prune_rest: bool = True
    device: str = "cpu"
    chunk_rays: int = 1 << 20
    threads: int | None = None

    @property
    def samples_per_pixel(self) -> int:
        return self.samples_per_axis ** 2

    def __post_init__(self) -> None:
        if self.max_depth < 1:
            raise ValueError(f"max_depth must be >= 1, got {self.max_depth}")
        if self.samples_per_axis < 1:
            raise ValueError(f"samples_per_axis must be >= 1, got {self.samples_per_axis}")
        if not (self.ior > 0 and self.ext_ior > 0):
            raise ValueError(f"refractive indices must be positive, got {self.ior}, {self.ext_ior}")
        if not (0 <= self.prune_threshold < 1):
            raise ValueError(f"prune_threshold must be in [0, 1), got {self.prune_threshold}")


@dataclass
class TwoBounce:
    """Two-bounce products of V views at the pixel centres, all (V, H, W, ...) on one device.

    mask: bool, the pixel-centre camera ray hits the mesh (= raycast.object_masks(mesh, cameras)).
    normal1, normal2: float32 (..., 3) unit smooth normals at the first hit P1 and at the second
        hit P2 of the refracted ray, camera frame (x = right, y = up, z = -forward), *outward*
        (pointing out of the object; at P1 normal1 faces the camera, z > 0, away from
        silhouettes). Zero where the hit does not exist.
    point1, point2: float32 (..., 3) world positions of P1, P2 (zero where undefined).
    depth1, depth2: float32 depth of P1, P2 along the camera's forward axis (as
        `Cameras.project`; P2 seen straight from the camera, not along the bent path); zero where
        undefined.
    hit2: bool, the ray refracted at P1 reaches a second interface P2.
    tir: bool, total internal reflection at P2 (the paper's M^tr).
    exit_dir: float32 (..., 3) world direction of the ray refracted out at P2 (zero where none).
    valid: bool, the two-bounce model explains the pixel: mask, the ray enters at P1 (arrives on
        the outer side of the smooth normal), reaches P2 from inside, refracts out without TIR,
        and the exit ray does not hit the mesh again (re-entry is beyond the paper's rendering
        layer).
    """

    mask: Tensor
    normal1: Tensor
    normal2: Tensor
    point1: Tensor
    point2: Tensor
    depth1: Tensor
    depth2: Tensor
    hit2: Tensor
    tir: Tensor
    exit_dir: Tensor
    valid: Tensor


@dataclass
class RenderStats:
    """Book-keeping of one `render_views` call.

    primary_rays: camera samples traced; rays_cast: all Embree rays of the image pass (the
    two-bounce pass adds up to 3 per pixel). pruned_energy / truncated_energy: throughput
    ended by pruning / by max_depth, as a fraction of all sample throughput (the first is
    compensated by the rest term when prune_rest). seconds: wall time of the call;
    seconds_two_bounce: of which the two-bounce maps.
    """

    primary_rays: int = 0
    rays_cast: int = 0
    pruned_energy: float = 0.0
    truncated_energy: float = 0.0
    seconds: float = 0.0
    seconds_two_bounce: float = 0.0


@dataclass
class RenderResult:
    """Output of `render_views` for V views of H x W.

    image: float32 (V, H, W, 3) linear radiance in the environment's units; pixels that miss
        the object show the (box-filtered) environment.
    two_bounce: the pixel-centre two-bounce maps (see `TwoBounce`); its fields are also exposed
        directly: mask, normal1, normal2, point1, point2, depth1, depth2, tir and
        two_bounce_valid (= two_bounce.valid).
    """

    image: Tensor
    two_bounce: TwoBounce
    stats: RenderStats = field(default_factory=RenderStats)

    mask = property(lambda self: self.two_bounce.mask)
    normal1 = property(lambda self: self.two_bounce.normal1)
    normal2 = property(lambda self: self.two_bounce.normal2)
    point1 = property(lambda self: self.two_bounce.point1)
    point2 = property(lambda self: self.two_bounce.point2)
    depth1 = property(lambda self: self.two_bounce.depth1)
    depth2 = property(lambda self: self.two_bounce.depth2)
    tir = property(lambda self: self.two_bounce.tir)
    two_bounce_valid = property(lambda self: self.two_bounce.valid)


# ---------------------------------------------------------------------------------------------
# the shared surface machinery
# ---------------------------------------------------------------------------------------------
class _Surface:
    """A mesh ready for the hot loop: Embree scene + per-triangle vertex normals as torch tensors.

    `cast` returns float32 torch tensors on `device`; the smooth normal is interpolated and
    normalized in float32 (Mitsuba interpolates its float32 PLY normals the same way).
    """

    def __init__(self, mesh: trimesh.Trimesh, device: str | torch.device = "cpu",
                 caster: RayCaster | None = None, threads: int | None = None):
        if mesh.is_watertight and mesh.volume < 0:
            # Inward normals would swap glass and air everywhere: refuse rather than render nonsense.
            raise ValueError("mesh is oriented inward (negative volume); call mesh.invert() first")
        self.caster = caster if caster is not None else RayCaster(mesh)
        self.device = torch.device(device)
        faces = torch.from_numpy(self.caster.faces)
        vn = torch.tensor(self.caster.vertex_normals, dtype=torch.float32)
        self.tri_normals = vn[faces].to(self.device)  # (F, 3 vertices, 3)
        self.threads = threads or os.cpu_count() or 1

    def cast(self, origins: Tensor, dirs: Tensor, offset: bool,
             threads: int | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """First hits of rays (N, 3) float32. Secondary rays (offset=True) start `epsilon` along
        their direction so they do not re-hit their own surface point.

        Returns the indices (K,) long of the rays that hit, their hit points (K, 3) and unit
        smooth normals (K, 3, outward). (Index tensors rather than boolean masks: torch
        re-runs nonzero() on every boolean indexing, which dominated the hot loop.)
        """
        if len(origins) == 0:
            empty = origins.new_zeros(0, 3)
            return torch.zeros(0, dtype=torch.long, device=self.device), empty, empty
        o_np = origins.detach().to("cpu", torch.float32).numpy()
        d_np = dirs.detach().to("cpu", torch.float32).numpy()
        t, face, u, v = self.caster.intersect_raw(o_np, d_np, offset=offset, threads=threads or self.threads)
        idx_np = np.flatnonzero(face >= 0)
        t_h = t[idx_np] + np.float32(self.caster.epsilon if offset else 0.0)  # from the caller's origin
        idx = torch.from_numpy(idx_np).to(self.device)
        f_h = torch.from_numpy(face[idx_np]).to(self.device)
        u_h = torch.from_numpy(u[idx_np]).to(self.device)[:, None]
        v_h = torch.from_numpy(v[idx_np]).to(self.device)[:, None]
        tn = self.tri_normals[f_h]
        n = torch.nn.functional.normalize((1 - u_h - v_h) * tn[:, 0] + u_h * tn[:, 1] + v_h * tn[:, 2], dim=-1)
        p = origins[idx] + torch.from_numpy(t_h).to(self.device)[:, None] * dirs[idx]
        return idx, p, n


def _dielectric(d: Tensor, n: Tensor, ior: float, ext_ior: float):
    """One smooth glass interface for rays d (N, 3) at outward smooth normals n (N, 3).

    The side is decided by the smooth normal, as in Mitsuba's `dielectric`: entering where
    dot(d, n) < 0. Returns (reflected dir, transmitted dir, Fresnel F (N,), tir (N,), entering (N,)).
    """
    entering = (d * n).sum(-1) < 0
    eta = torch.where(entering, torch.full_like(d[:, 0], ext_ior / ior), torch.full_like(d[:, 0], ior / ext_ior))
    r, t, f, tir = interface(d, n, eta)
    return r, t, f, tir, entering


# ---------------------------------------------------------------------------------------------
# two-bounce maps
# ---------------------------------------------------------------------------------------------
def trace_two_bounce(mesh: trimesh.Trimesh, cameras: Cameras, ior: float = IOR_GLASS,
                     ext_ior: float = IOR_AIR, *, device: str | torch.device = "cpu",
                     caster: RayCaster | None = None, threads: int | None = None) -> TwoBounce:
    """The two-bounce products of `mesh` seen by `cameras`, at pixel centres (see `TwoBounce`).

    mesh: closed, consistently oriented (outward) triangle mesh, world frame. cameras: V views
    of H x W. caster: reuse an existing Embree scene of `mesh`. Costs at most 3 rays per pixel.
    """
    return _two_bounce(_Surface(mesh, device, caster, threads), cameras, ior, ext_ior)


def _two_bounce(surf: _Surface, cameras: Cameras, ior: float, ext_ior: float) -> TwoBounce:
    dev = surf.device
    V, H, W = cameras.num_views, cameras.height, cameras.width
    # Pixel-centre rays built in float64 then rounded to float32, exactly as raycast.object_masks
    # does, so `mask` equals object_masks(mesh, cameras) bit for bit.
    o64, d64 = cameras.to(dtype=torch.float64, device="cpu").pixel_rays()
    o0 = o64.reshape(-1, 3).to(torch.float32).to(dev)
    d0 = d64.reshape(-1, 3).to(torch.float32).to(dev)
    N = o0.shape[0]
    f32 = dict(dtype=torch.float32, device=dev)
    zeros3 = lambda: torch.zeros(N, 3, **f32)  # noqa: E731
    no = lambda: torch.zeros(N, dtype=torch.bool, device=dev)  # noqa: E731

    # hit 1: the camera ray meets the surface and refracts in
    i1, p1h, n1h = surf.cast(o0, d0, offset=False)
    _, t1h, _, tir1h, enter1h = _dielectric(d0[i1], n1h, ior, ext_ior)
    go = (enter1h & ~tir1h).nonzero().squeeze(-1)  # a back-facing smooth normal at P1 = "inside"

    # hit 2: the refracted ray meets the surface from inside and refracts out
    j2, p2h, n2h = surf.cast(p1h[go], t1h[go], offset=True)
    i2 = i1[go[j2]]
    _, t2h, _, tir2h, enter2h = _dielectric(t1h[go[j2]], n2h, ior, ext_ior)
    out = (~enter2h & ~tir2h).nonzero().squeeze(-1)

    # the exit ray: does it come back onto the object?
    j3, _, _ = surf.cast(p2h[out], t2h[out], offset=True)
    i3 = i2[out]

    point1, normal1, point2, normal2, exit_dir = zeros3(), zeros3(), zeros3(), zeros3(), zeros3()
    point1[i1], normal1[i1] = p1h, n1h
    point2[i2], normal2[i2] = p2h, n2h
    exit_dir[i3] = t2h[out]
    hit1, hit2, tir, valid = no(), no(), no(), no()
    hit1[i1] = True
    hit2[i2] = True
    tir[i2] = tir2h & ~enter2h
    valid[i3] = True
    valid[i3[j3]] = False

    cams = cameras.to(dtype=torch.float32, device=dev)
    shape = (V, H, W)

    def depth(p: Tensor, defined: Tensor) -> Tensor:
        p = p.view(V, H * W, 3)
        z = ((p - cams.origin[:, None]) * cams.forward[:, None]).sum(-1)
        return torch.where(defined.view(V, -1), z, torch.zeros_like(z)).view(shape)

    to_cam = lambda n: cams.world_to_camera(n.view(V, H, W, 3))  # noqa: E731
    return TwoBounce(
        mask=hit1.view(shape), normal1=to_cam(normal1), normal2=to_cam(normal2),
        point1=point1.view(V, H, W, 3), point2=point2.view(V, H, W, 3),
        depth1=depth(point1, hit1), depth2=depth(point2, hit2), hit2=hit2.view(shape),
        tir=tir.view(shape), exit_dir=exit_dir.view(V, H, W, 3), valid=valid.view(shape))


# ---------------------------------------------------------------------------------------------
# full light transport
# ---------------------------------------------------------------------------------------------
def mean_radiance(envmap: EnvironmentMap) -> Tensor:
    """Solid-angle mean radiance (3,) of an equirectangular map (rows span the poles, as in
    `EnvironmentMap.lookup_uv`, so row i sits at polar angle pi i / (H - 1))."""
    H = envmap.height
    theta = torch.linspace(0, math.pi, H, dtype=torch.float64, device=envmap.radiance.device)
    w = torch.sin(theta)
    if H > 1:  # the pole rows stand for a half-row band each
        w[0] = w[-1] = math.sin(math.pi / (2 * (H - 1))) / 4
    rows = envmap.radiance.to(torch.float64).mean(dim=1)  # (H, 3)
    return (rows * w[:, None]).sum(0) / w.sum()


def _hash32(x: Tensor) -> Tensor:
    """PCG-style 32-bit integer hash (Jarzynski & Olano 2020) of int64 values in [0, 2^32),
    in int64 arithmetic that never overflows (every product stays below 2^62)."""
    x = (x * 747796405 + 2891336453) & 0xFFFFFFFF
    word = ((torch.bitwise_right_shift(x, torch.bitwise_right_shift(x, 28) + 4) ^ x) * 277803737) & 0xFFFFFFFF
    return torch.bitwise_right_shift(word, 22) ^ word


class _CameraSamples:
    """Stratified (optionally jittered) sub-pixel camera samples of all views, in blocks.

    Samples of one view are ordered (sub-pixel k, row, col); a block takes the same index range
    [a, b) from every view, so `Cameras.directions_at` gets (V, n) coordinates. The jitter is a
    hash of (seed, view, sample index): a sample is the same whichever block or thread draws it.
    """

    def __init__(self, cameras: Cameras, cfg: RenderConfig, device: torch.device):
        self.cams = cameras.to(dtype=torch.float32, device=device)
        self.V, self.H, self.W = cameras.num_views, cameras.height, cameras.width
        self.s, self.jitter, self.device = cfg.samples_per_axis, cfg.jitter, device
        self.per_view = self.s * self.s * self.H * self.W
        self.seed_key = int(_hash32(torch.tensor(int(cfg.seed) & 0xFFFFFFFF)))
        self.view_base = (torch.arange(self.V, device=device) * (self.H * self.W))[:, None]

    def blocks(self, size: int) -> list[tuple[int, int]]:
        """The per-view index range cut into blocks of `size` samples per view."""
        return [(a, min(a + size, self.per_view)) for a in range(0, self.per_view, size)]

    def take(self, a: int, b: int) -> tuple[Tensor, Tensor, Tensor]:
        """Samples [a, b) of every view: origins, unit dirs (V * (b - a), 3) float32 world,
        and each ray's flat pixel index v * H * W + row * W + col (V * (b - a),) long."""
        H, W, s, V, n = self.H, self.W, self.s, self.V, b - a
        idx = torch.arange(a, b, device=self.device)
        k, pix = idx // (H * W), idx % (H * W)
        si, sj = k // s, k % s
        if self.jitter:
            key = (torch.arange(V, device=self.device)[:, None] * self.per_view + idx[None]) & 0xFFFFFFFF
            h1 = _hash32(key ^ self.seed_key)
            h2 = _hash32(h1)
            # 24 random bits: exactly representable in float32, so the jitter stays < 1.
            jx = torch.bitwise_right_shift(h1, 8).to(torch.float32) * 2.0 ** -24
            jy = torch.bitwise_right_shift(h2, 8).to(torch.float32) * 2.0 ** -24
        else:
            jx = jy = torch.full((V, n), 0.5, dtype=torch.float32, device=self.device)
        x = pix % W + (sj + jx) / s  # (V, n) continuous image coordinates
        y = pix // W + (si + jy) / s
        d = self.cams.directions_at(x, y).reshape(-1, 3)
        o = self.cams.origin[:, None, :].expand(V, n, 3).reshape(-1, 3)
        return o, d, (self.view_base + pix[None]).reshape(-1)


def _transport(surf: _Surface, env: EnvironmentMap, samples: _CameraSamples,
               blocks: list[tuple[int, int]], accum: Tensor, cfg: RenderConfig, rest: Tensor,
               stats: RenderStats, embree_threads: int, traced: Tensor | None = None) -> None:
    """Trace the camera samples of `blocks` through the glass, adding radiance into accum
    (V*H*W, 3). traced: (V*H*W,) bool, the pixels whose samples are traced (None: all); the
    others read the environment along their camera ray, the mesh left out.

    A wavefront: each step casts every live branch once. Deterministic branching: at every
    interface both the reflected (weight F) and the transmitted (1 - F) branch go on; branches
    under `prune_threshold` end (their weight x the mean environment radiance goes to the rest
    term); a branch that meets its (max_depth + 1)-th interface is dropped, as Mitsuba does.
    Escaping branches read the environment in their direction. The next block of camera samples
    joins whenever there is room, so the long, thin tails of deep paths (total internal
    reflection traps) ride along with fresh work instead of costing Python steps of their own.
    """
    dev = accum.device
    empty3 = torch.zeros(0, 3, dtype=torch.float32, device=dev)
    o, d = empty3, empty3
    p = torch.zeros(0, dtype=torch.long, device=dev)
    w = torch.zeros(0, dtype=torch.float32, device=dev)
    depth = torch.zeros(0, dtype=torch.int16, device=dev)
    todo = list(reversed(blocks))
    while len(o) or todo:
        while todo and (len(o) == 0 or len(o) + samples.V * (todo[-1][1] - todo[-1][0]) <= cfg.chunk_rays):
            o_n, d_n, p_n = samples.take(*todo.pop())
            stats.primary_rays += len(o_n)
            if traced is not None:
                untraced = ~traced[p_n]
                if bool(untraced.any()):
                    accum.index_add_(0, p_n[untraced], env.lookup(d_n[untraced]))
                    keep = (~untraced).nonzero().squeeze(-1)
                    o_n, d_n, p_n = o_n[keep], d_n[keep], p_n[keep]
            o, d, p = torch.cat([o, o_n]), torch.cat([d, d_n]), torch.cat([p, p_n])
            w = torch.cat([w, torch.ones(len(o_n), dtype=torch.float32, device=dev)])
            depth = torch.cat([depth, torch.zeros(len(o_n), dtype=torch.int16, device=dev)])
        # Camera rays are offset too: harmless (the camera is far from the object) and it keeps
        # one Embree call per step.
        ih, ph, nh = surf.cast(o, d, offset=True, threads=embree_threads)
        stats.rays_cast += len(o)
        if len(ih) < len(o):  # escaped: read the environment
            esc = torch.ones(len(o), dtype=torch.bool, device=dev)
            esc[ih] = False
            ie = esc.nonzero().squeeze(-1)
            accum.index_add_(0, p[ie], w[ie, None] * env.lookup(d[ie]))
        d, p, w, depth = d[ih], p[ih], w[ih], depth[ih]
        over = depth >= cfg.max_depth
        if bool(over.any()):
            stats.truncated_energy += float(w[over].sum())
            ok = (~over).nonzero().squeeze(-1)
            d, p, w, depth, ph, nh = d[ok], p[ok], w[ok], depth[ok], ph[ok], nh[ok]
        r, t, f, tir, _ = _dielectric(d, nh, cfg.ior, cfg.ext_ior)
        # Both branches; a TIR branch has F = 1 and no transmitted twin, so it is never split.
        it = (~tir).nonzero().squeeze(-1)
        o = torch.cat([ph, ph[it]])
        d = torch.cat([r, t[it]])
        p = torch.cat([p, p[it]])
        w = torch.cat([w * f, (w * (1 - f))[it]])
        depth = torch.cat([depth, depth[it]]) + 1
        small = w < cfg.prune_threshold
        if bool(small.any()):
            i_s = small.nonzero().squeeze(-1)
            ws = w[i_s]
            stats.pruned_energy += float(ws.sum())
            if cfg.prune_rest:
                accum.index_add_(0, p[i_s], ws[:, None] * rest)
            keep = (~small).nonzero().squeeze(-1)
            o, d, p, w, depth = o[keep], d[keep], p[keep], w[keep], depth[keep]


def render_views(mesh: trimesh.Trimesh, envmap: EnvironmentMap, cameras: Cameras,
                 config: RenderConfig | None = None, region: Tensor | None = None) -> RenderResult:
    """Render a smooth clear-glass `mesh` under the distant `envmap` from every view of `cameras`.

    mesh: closed, outward-oriented triangle mesh (world frame), shaded with its smooth vertex
    normals. envmap: equirectangular linear radiance. Returns `RenderResult` with image
    (V, H, W, 3) float32 and the pixel-centre two-bounce maps (`trace_two_bounce`'s code, on the
    same Embree scene).

    Rays of all views are traced together: the camera samples are cut into blocks that are
    dealt round-robin to `config.threads` worker threads (torch and Embree release the GIL),
    each running a wavefront of at most `chunk_rays` live branches; the only Python loop is over
    wavefront steps. Each worker accumulates into its own image and the images are summed in
    worker order, so a render is bit-for-bit reproducible for a given seed and thread count
    (other thread counts differ by float rounding only: the samples themselves are fixed by the
    seed). Torch runs single-threaded during the image pass (restored after).

    region: (V, H, W) bool, where the image is needed (a comparison with photos reads it inside
    their masks and the mesh's silhouette only): then only the samples of the region's pixels and
    of the silhouette's (`TwoBounce.mask`) are traced, each along the same path as without it, and
    the others read the environment along their camera ray (at an edge a jittered sample of a
    pixel whose centre misses the mesh might have met it); ~1/3 of a 10-view re-rendering's rays
    are background pixels'. Where every sample fits one wavefront (`chunk_rays`; a 240x180
    10-view re-rendering at 1 spp does) the region's pixels are the same to the bit; where later
    blocks of samples join, they join sooner and a pixel's contributions may be summed in
    another order (~1e-7).
    """
    cfg = config or RenderConfig()
    start = time.perf_counter()
    dev = torch.device(cfg.device)
    workers = max(1, int(cfg.threads or os.cpu_count() or 1))
    surf = _Surface(mesh, dev, threads=workers)
    stats = RenderStats()
    two = _two_bounce(surf, cameras, cfg.ior, cfg.ext_ior)  # one thread of big torch ops: keep torch's pool
    stats.seconds_two_bounce = time.perf_counter() - start
    # Torch single-threaded: our parallelism is one Python thread per worker, and OpenMP teams
    # inside each would oversubscribe the cores (their spin-waits tripled a render's CPU time).
    with torch_threads(1):
        env = envmap.to(device=dev, dtype=torch.float32)
        rest = mean_radiance(envmap).to(device=dev, dtype=torch.float32)
        samples = _CameraSamples(cameras, cfg, dev)
        V, H, W = samples.V, samples.H, samples.W
        # Blocks of ~1/4 wavefront: small enough to top a wavefront up, big enough to amortize.
        blocks = samples.blocks(max(1, cfg.chunk_rays // (4 * V)))
        workers = min(workers, len(blocks))
        traced = None if region is None else (region.to(dev).bool() | two.mask).reshape(-1)

        def work(i: int) -> tuple[Tensor, RenderStats]:
            acc = torch.zeros(V * H * W, 3, dtype=torch.float32, device=dev)
            st = RenderStats()
            _transport(surf, env, samples, blocks[i::workers], acc, cfg, rest, st, embree_threads=1, traced=traced)
            return acc, st

        if workers == 1:
            parts = [work(0)]
        else:
            with ThreadPoolExecutor(workers) as pool:
                parts = list(pool.map(work, range(workers)))
        accum = parts[0][0]
        for acc, _ in parts[1:]:
            accum += acc
        for _, st in parts:
            stats.primary_rays += st.primary_rays
            stats.rays_cast += st.rays_cast
            stats.pruned_energy += st.pruned_energy
            stats.truncated_energy += st.truncated_energy

    image = (accum / cfg.samples_per_pixel).view(V, H, W, 3)
    total = max(stats.primary_rays, 1)
    stats.pruned_energy /= total
    stats.truncated_energy /= total
    stats.seconds = time.perf_counter() - start
    return RenderResult(image=image, two_bounce=two, stats=stats)


__all__ = ["RenderConfig", "RenderResult", "RenderStats", "TwoBounce", "render_views",
           "trace_two_bounce", "mean_radiance"]
