"""The refine stage against independent references: an ellipsoid's silhouettes ray cast by Embree
(`object_masks`) from a paper rig are the masks; a shrunken, lumpy copy of it must be pulled onto
them and closer to the ellipsoid, a stray blob in one mask must get that view down-weighted and
named, and the ellipsoid itself must not be made worse."""

from __future__ import annotations

import dataclasses
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

from lookingglass.config import STAGES, PipelineConfig
from lookingglass.data.rigs import paper_rig
from lookingglass.errors import ConfigError
from lookingglass.hull import HullConfig, carve_visual_hull
from lookingglass.metrics import shape_metrics
from lookingglass.normals.inputs import NormalInputs
from lookingglass.normals.predict import NormalMaps
from lookingglass.normals.stage import second_pass
from lookingglass.physics.constants import IOR_GLASS
from lookingglass.physics.environment import EnvironmentMap
from lookingglass.refine import (RefineConfig, carve_by_hull, local_thickness, refine_pass, refine_surface,
                                 silhouette_iou, uniform_laplacian, worse_measures)
from lookingglass.render.raycast import object_masks
from lookingglass.render.tracer import RenderConfig, render_views, trace_two_bounce

# a coarser surface than the default (0.018) keeps the tests fast; the method is the same. One round and
# one pass: the tests measure what a round does (the penalty rounds, `silhouette_retries`, and the passes
# have their own tests)
CONFIG = RefineConfig(edge_length=0.035, silhouette_retries=0, passes=1)


def ellipsoid_scene(width: int = 320, height: int = 240):
    """The ellipsoid, a 10-view paper rig at width x height, its masks and their visual hull."""
    gt = trimesh.creation.icosphere(subdivisions=5)
    gt.vertices = gt.vertices * [0.95, 0.6, 0.75] + [0.05, -0.03, 0.02]
    cameras = paper_rig(10, rng=3, width=width, height=height)
    masks = object_masks(gt, cameras, samples_per_axis=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hull = carve_visual_hull(masks, cameras, HullConfig(resolution=64, num_threads=1))
    return gt, cameras, masks, hull


@pytest.fixture(scope="module")
def scene():
    return ellipsoid_scene()


def lumpy_shrunken(gt: trimesh.Trimesh, scale: float = 0.97, lumps: float = 0.01) -> trimesh.Trimesh:
    """gt scaled by `scale` about its centre with smooth radial lumps of +-`lumps`: inside every
    mask (the default: about 2 px inside the masks at 320x240, like a network surface's offsets)."""
    c = gt.vertices.mean(axis=0)
    p = gt.vertices - c
    lumps = scale + lumps * np.sin(7 * p[:, 0]) * np.cos(6 * p[:, 1]) * np.sin(5 * p[:, 2] + 1)
    return trimesh.Trimesh(c + p * lumps[:, None], gt.faces, process=False)


def test_uniform_laplacian_rows_sum_to_zero_and_vanish_on_constants():
    box = trimesh.creation.box()
    lap = uniform_laplacian(np.asarray(box.faces), len(box.vertices))
    np.testing.assert_allclose(lap @ np.ones(len(box.vertices)), 0, atol=1e-12)
    np.testing.assert_allclose(lap.diagonal(), 1)


def test_local_thickness_is_the_diameter_of_a_sphere_and_a_plate():
    """Along the inward normal of a sphere of radius r the far side is 2r away (the chord through the
    centre; the faces lie at most the sagitta inside the sphere); through a plate, its thickness."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    t = local_thickness(np.asarray(sphere.vertices), np.asarray(sphere.faces), smoothing=0)
    np.testing.assert_allclose(t, 1.0, rtol=2e-3)
    plate = remesh_box((1.0, 1.0, 0.1))
    v = np.asarray(plate.vertices)
    middle = (np.abs(v[:, :2]).max(axis=1) < 0.3)  # big faces, away from the rims
    t = local_thickness(v, np.asarray(plate.faces), smoothing=0)
    np.testing.assert_allclose(t[middle], 0.1, rtol=0.02)


def remesh_box(extents) -> trimesh.Trimesh:
    """A box with its faces split into small triangles (vertices inside the big faces)."""
    box = trimesh.creation.box(extents)
    for _ in range(5):
        box = box.subdivide()
    return box


def test_fairing_weakened_on_thin_parts_keeps_a_rod_on_its_masks():
    """Fairing (|L x|^2) pulls hardest where the curvature is largest, ~1/r^3 on a rod of radius r;
    weakened there by (thickness / fair_thickness)^2, a thin rod stays on its masks better."""
    rod = trimesh.creation.capsule(height=1.4, radius=0.07, count=[32, 32])
    rod.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    cameras = paper_rig(10, rng=3, width=320, height=240)
    masks = object_masks(rod, cameras, samples_per_axis=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hull = carve_visual_hull(masks, cameras, HullConfig(resolution=64, num_threads=1))
    # the weights this was measured with (before 2026-11-26's): fairing 60 x the silhouettes', which shrinks the rod
    # and plain fairing (fair_curvature_rings 0): keeping the curvature also holds the rod (worst view 0.978)
    strong = dataclasses.replace(CONFIG, silhouette_weight=1.0, fair_weight=60.0, silhouette_width_power=2.0,
                                 fair_width_power=1.0, fair_curvature_rings=0, fair_thickness=0.0)
    uniform = silhouette_iou(refine_surface(rod, hull, masks, cameras, strong).refined, cameras, masks)
    thin = dataclasses.replace(strong, fair_thickness=0.4)
    weakened = silhouette_iou(refine_surface(rod, hull, masks, cameras, thin).refined, cameras, masks)
    # measured: worst view 0.972 -> 0.980, mean 0.983 -> 0.987
    assert weakened.min() >= uniform.min() + 0.004 and weakened.mean() > uniform.mean(), (uniform, weakened)


def test_fairing_that_keeps_the_curvature_does_not_shrink_a_smooth_shape():
    """Plain fairing pulls the Laplacian of the positions toward 0, which shrinks a curved surface
    wherever the silhouettes hold it weakly (coarse masks); pulled toward its own neighbourhood
    average (fair_curvature_rings), it irons out only what varies faster. The ellipsoid itself, its
    128x96 masks, the fairing 5000 (25 x the default of the time): plain loses 2.5% of the volume, the other 0.3%
    (measured)."""
    from lookingglass.refine import fair_curvature_share

    gt, cameras, masks, hull = ellipsoid_scene(128, 96)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        heavy = dataclasses.replace(CONFIG, fair_weight=5000.0, fair_width_power=0.0, silhouette_weight=2.0,
                                    silhouette_width_power=3.0, normal_iterations=0)
        keeping = dataclasses.replace(heavy, fair_curvature_rings=4)
        plain = refine_surface(gt, hull, masks, cameras, dataclasses.replace(heavy, fair_curvature_rings=0)).refined
        kept = refine_surface(gt, hull, masks, cameras, keeping).refined
    assert fair_curvature_share(dataclasses.replace(heavy, fair_curvature_rings=0), 128) == 0.0
    assert plain.volume < 0.985 * gt.volume and abs(kept.volume / gt.volume - 1) < 0.005, (plain.volume, kept.volume)
    assert silhouette_iou(kept, cameras, masks).min() > silhouette_iou(plain, cameras, masks).min() + 0.01
    # and it still irons out lumps: from a lumpy copy, CDN-mean 2.66 -> 1.99 (measured; 3.74 without fairing,
    # where the silhouettes pull ridges along the contours)
    lumpy = lumpy_shrunken(gt, scale=1.0, lumps=0.02)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        faired = refine_surface(lumpy, hull, masks, cameras, keeping).refined
        unfaired = refine_surface(lumpy, hull, masks, cameras, dataclasses.replace(keeping, fair_weight=0.0)).refined
    cdn = {name: shape_metrics(m, gt)["cdn_mean"] for name, m in (("start", lumpy), ("faired", faired),
                                                                   ("unfaired", unfaired))}
    assert cdn["faired"] < 0.85 * cdn["start"] and cdn["faired"] < 0.7 * cdn["unfaired"], cdn
    # all of it on masks at most half silhouette_width wide, none at silhouette_width and above
    assert [fair_curvature_share(keeping, w) for w in (128, 240, 360, 480, 1920)] == [1.0, 1.0, 0.5, 0.0, 0.0]


def test_shrunken_lumpy_mesh_is_pulled_onto_the_masks(scene):
    gt, cameras, masks, hull = scene
    start = lumpy_shrunken(gt)
    iou_start = silhouette_iou(start, cameras, masks)
    assert iou_start.max() < 0.95  # the test means something: the input misses the masks clearly
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # consistent views: no view is down-weighted
        result = refine_surface(start, hull, masks, cameras, CONFIG)
    report = result.report
    assert report["kept"] == "refined" and report["down_weighted_views"] == []
    iou = silhouette_iou(result.mesh, cameras, masks)
    assert iou.min() >= 0.98, iou
    np.testing.assert_allclose(report["silhouette_iou_after"], iou, atol=1e-4)
    # closer to the ellipsoid than the input, in Chamfer distance and normals
    before, after = shape_metrics(start, gt), shape_metrics(result.mesh, gt)
    assert after["cd"] < 0.8 * before["cd"], (before, after)
    # A known limit, measured and kept in view here: each pull is local (anchor_weight), so on a
    # smooth input the moved contour generators leave shallow ridges and the normals get worse
    # (CDN-mean 1.7 -> about 9 degrees on this ellipsoid); on the networks' lumpy surfaces the
    # fairing wins (docs/results.md). This bounds the damage.
    assert after["cdn_mean"] < 12, (before, after)
    # the optimized terms went down, nothing folded, the mesh is still closed
    assert report["terms_after"]["silhouette_px2"] < 0.2 * report["terms_before"]["silhouette_px2"]
    assert report["terms_after"]["smooth"] <= report["terms_before"]["smooth"]
    assert report["terms_after"]["folds"] == 0 and result.mesh.is_watertight


def test_a_surface_far_short_of_a_mask_is_pulled_out(scene):
    """The ellipsoid's end cut flat at x = 0.62 falls ~30 px short of some masks (320x240): the rim
    vertices within `band_px` of the boundary pull the contour out, and as it moves the rest come
    within reach. The default band (24 px since the 5-view nut, session 52, whose PNet surface left
    a crescent of its mask uncovered) gets the worst view from 0.86 to >= 0.94 (measured 0.948 with
    session 57's weights at 320 px, and before); 12 px, the old default, stalls lower (measured
    0.927, 0.903 before)."""
    gt, cameras, masks, hull = scene
    cut = gt.copy()
    cut.vertices = np.column_stack([np.minimum(gt.vertices[:, 0], 0.62), gt.vertices[:, 1:]])
    assert silhouette_iou(cut, cameras, masks).min() < 0.87
    config = dataclasses.replace(CONFIG, rerender_width=0)
    assert config.band_px == 24
    worst = {band: silhouette_iou(refine_surface(cut, hull, masks, cameras,
                                                 dataclasses.replace(config, band_px=band)).refined,
                                  cameras, masks).min() for band in (12.0, config.band_px)}
    assert worst[config.band_px] >= 0.94 and worst[12.0] < worst[config.band_px] - 0.01, worst


def test_views_still_short_of_their_masks_pull_harder_in_another_round(scene):
    """A penalty method on the views (`silhouette_retries`): with a silhouette weight too weak for the
    fairing (1 against the default 20, as on coarse masks), the shrunken, lumpy ellipsoid keeps views
    below the IoU target after one round (measured: worst 0.976); rerun from the input with those
    views' silhouette weight tripled, every view reaches it (0.984), and the round whose kept mesh
    matches its worst view best is returned, each round's factors in report.json."""
    gt, cameras, masks, hull = scene
    start = lumpy_shrunken(gt)
    defaults = RefineConfig()
    assert defaults.silhouette_retries == 2 and defaults.silhouette_retry_factor == 3
    config = dataclasses.replace(CONFIG, rerender_width=0, silhouette_weight=1.0, silhouette_retries=2)
    one = refine_surface(start, hull, masks, cameras, dataclasses.replace(config, silhouette_retries=0))
    iou_one = silhouette_iou(one.mesh, cameras, masks)
    assert iou_one.min() < config.silhouette_iou_target and "silhouette_rounds" not in one.report
    more = refine_surface(start, hull, masks, cameras, config)
    rounds = more.report["silhouette_rounds"]
    assert 2 <= len(rounds) <= 3
    # the first round is the one-round run; the next triples the views that run left short
    assert rounds[0]["worst_iou"] == pytest.approx(iou_one.min(), abs=1e-4)
    np.testing.assert_array_equal(rounds[0]["boost"], 1.0)
    np.testing.assert_array_equal(rounds[1]["boost"], np.where(iou_one < config.silhouette_iou_target, 3.0, 1.0))
    worst = [r["worst_iou"] for r in rounds]
    assert more.report["silhouette_round"] == int(np.argmax(worst))
    iou_more = silhouette_iou(more.mesh, cameras, masks)
    assert iou_more.min() == pytest.approx(max(worst), abs=1e-4)
    assert iou_more.min() >= config.silhouette_iou_target, (iou_one.min(), worst)
    assert more.report["kept"] == "refined" and more.mesh.is_watertight
    assert more.report["silhouette_rounds_ended"] == "target met"


def test_rounds_that_do_not_help_end_early(scene):
    """Rounds whose worst view is no better than the best round's end the rounds (`silhouette_round_gain`;
    the first is followed by one milder round, `silhouette_retry_backoff`): with no silhouette pull at
    all (weight 0, so no factor changes anything), the fairing leaves the shrunken ellipsoid short of
    its masks in every round, and the third round is the last, not one of four."""
    gt, cameras, masks, hull = scene
    config = dataclasses.replace(CONFIG, rerender_width=0, silhouette_weight=0.0, silhouette_retries=3)
    result = refine_surface(lumpy_shrunken(gt), hull, masks, cameras, config)
    rounds = result.report["silhouette_rounds"]
    # the second round, no better, is followed by one more mildly pulled (silhouette_retry_backoff), no better
    # either, and that is the last, not one of four
    assert len(rounds) == 3 and result.report["silhouette_rounds_ended"] == "stalled", rounds
    assert rounds[0]["worst_iou"] < config.silhouette_iou_target
    for later in rounds[1:]:
        assert later["worst_iou"] == pytest.approx(rounds[0]["worst_iou"], abs=config.silhouette_round_gain)
    assert max(rounds[2]["boost"]) == pytest.approx(3 ** 0.5, abs=1e-3)
    assert result.report["silhouette_round"] == 0


def stand_in_rounds(monkeypatch, worst, kept, config, seed=None):
    """`refine_pass` (one pass of the stage) over stand-in rounds whose kept meshes' worst views are `worst` (view 0 the
    worst in every round, the other three at 0.99), each the refined mesh or, where `kept` says so,
    the input: its result, and each round's view factors (boost)."""
    import lookingglass.refine as refine

    V, calls = 4, []
    kept = kept or ["refined"] * len(worst)

    def one_round(mesh, hull, masks, cameras, config, weights, boost, capture, normals, start):
        calls.append(boost.copy())
        return SimpleNamespace(report={"kept": kept[len(calls) - 1], "seconds": 1.0}, casts=len(calls) - 1)

    monkeypatch.setattr(refine, "_refine_once", one_round)
    monkeypatch.setattr(refine, "cast_iou", lambda casts, masks: np.array([worst[casts], 0.99, 0.99, 0.99]))
    # no input to cut: the stand-in rounds take none
    result = refine_pass(None, SimpleNamespace(view_coverage=np.ones(V)), np.zeros((V, 2, 2), bool), None,
                            dataclasses.replace(config, input_carve=False), seed=seed)
    return result, calls


def test_a_pass_seeded_with_a_pull_starts_its_rounds_from_it(monkeypatch):
    """A later pass after one that fell short starts from the views' factors that pass ended with
    (`seed["boost"]`), and its next round multiplies the still short view's on from there."""
    result, calls = stand_in_rounds(monkeypatch, [0.95, 0.985], None, RefineConfig(),
                                    seed={"boost": np.array([3.0, 1.0, 1.0, 1.0])})
    assert [c.tolist() for c in calls] == [[3.0, 1.0, 1.0, 1.0], [9.0, 1.0, 1.0, 1.0]]
    assert result.report["silhouette_rounds"][0]["boost"] == [3.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("worst, rounds, returned, ended, kept", [
    ([0.95, 0.985], 2, 1, "target met", None),
    ([0.95, 0.97, 0.975], 3, 2, "rounds spent", None),
    ([0.95, 0.9509, 0.99], 2, 1, "stalled", None),  # 0.0009 is no gain: the third round never runs
    ([0.95, 0.9511, 0.96], 3, 2, "rounds spent", None),
    ([0.95, 0.94, 0.99], 2, 0, "stalled", None),  # a worse round is the last, and not the one returned
    # a round that keeps its refined mesh beats one that keeps the input (20-view test scene 30)
    ([0.9787, 0.9775], 2, 1, "stalled", ["input", "refined"]),
    ([0.95, 0.97, 0.96], 3, 2, "stalled", ["refined", "input", "refined"]),
    ([0.95, 0.95], 2, 0, "stalled", ["input", "input"]),  # none refined: the input, once more at most
])
def test_the_rounds_run_while_they_raise_the_worst_view(monkeypatch, worst, rounds, returned, ended, kept):
    """The rounds' bookkeeping alone (`refine_surface` over stand-in rounds whose kept meshes' worst
    views are `worst`, each the refined mesh or, where `kept` says so, the input): a round runs while
    a view is below the target, the retries last and the previous round raised the best worst view by
    more than silhouette_round_gain (0.001); of the rounds that keep their refined mesh (else of all)
    the one with the best worst view is returned."""
    config = RefineConfig(silhouette_retry_backoff=False)  # the back-off: the next test
    assert config.silhouette_retries == 2 and config.silhouette_round_gain == 0.001
    result, calls = stand_in_rounds(monkeypatch, worst, kept, config)
    assert len(calls) == rounds and result.casts == returned
    assert result.report["silhouette_round"] == returned and result.report["silhouette_rounds_ended"] == ended
    assert [r["worst_iou"] for r in result.report["silhouette_rounds"]] == worst[:rounds]
    # only the view left short pulls harder, 3 x a round
    np.testing.assert_array_equal(np.array(calls), [[3.0 ** k, 1, 1, 1] for k in range(rounds)])


R3 = 3.0 ** 0.5


@pytest.mark.parametrize("worst, retries, boosts, returned, ended, kept", [
    # a round that overshoots (val480's key at 3 x: 0.9795 -> 0.9774) is followed by one from the best
    # round with the factor's square root, not by the end
    ([0.9795, 0.9774, 0.9833], 2, [1, 3, R3], 2, "target met", None),
    # ... and returned only where it lands every view on the target (10-view test scene 0: 0.9665 -> 0.9685
    # cost 0.46 degrees of CDN-mean)
    ([0.95, 0.94, 0.96], 2, [1, 3, R3], 0, "rounds spent", None),
    ([0.95, 0.9509, 0.97], 2, [1, 3, R3], 1, "rounds spent", None),  # 0.0009 is no gain: backed off
    ([0.95, 0.94, 0.93], 2, [1, 3, R3], 0, "stalled", None),  # backed off once only
    # a round that helped pulls on with the milder factor: 1, 3, (stalls at 9) 3 x sqrt(3), then x sqrt(3) again
    ([0.95, 0.96, 0.955, 0.965, 0.97], 4, [1, 3, 9, 3 * R3, 9], 4, "rounds spent", None),
    ([0.95, 0.96, 0.955, 0.965, 0.962], 4, [1, 3, 9, 3 * R3, 9], 4, "stalled", None),  # the best eligible
    ([0.95, 0.96, 0.955, 0.958], 4, [1, 3, 9, 3 * R3], 1, "stalled", None),  # the second stall ends them
    # the last of the retries stalls: a back-off round over them (10-view test scene 3: 0.9706, 0.9790, 0.9795
    # at 9 x, 0.9800 at 3 x sqrt(3)) ...
    ([0.9706, 0.979, 0.9795, 0.98], 2, [1, 3, 9, 3 * R3], 3, "target met", None),
    ([0.95, 0.97, 0.96, 0.975], 2, [1, 3, 9, 3 * R3], 1, "rounds spent", None),  # short: not returned
    ([0.95, 0.97, 0.96, 0.965], 2, [1, 3, 9, 3 * R3], 1, "stalled", None),
    ([0.95, 0.96, 0.97], 2, [1, 3, 9], 2, "rounds spent", None),  # ... not after one that helped
    ([0.95, 0.94, 0.96], 1, [1, 3, R3], 0, "rounds spent", None),  # one retry, one round over it
    ([0.95], 0, [1], 0, None, None),  # no retries: one round, no back-off
    # the round returned is still chosen refined-first (20-view test scene 30)
    ([0.9787, 0.9775, 0.978], 2, [1, 3, R3], 1, "stalled", ["input", "refined", "refined"]),
    ([0.9787, 0.9775, 0.9801], 2, [1, 3, R3], 2, "target met", ["input", "refined", "refined"]),
])
def test_a_round_that_overshoots_is_retried_more_mildly(monkeypatch, worst, retries, boosts, returned, ended, kept):
    """`silhouette_retry_backoff` (on by default), the rounds' bookkeeping alone as above: a round
    that does not raise the best worst view is followed, once, by a round from the best round's
    factors with the short views' factor's square root, returned only where it meets the target;
    the rounds then go on at that factor. Where the last of the retries stalls, the back-off is one
    round over them."""
    config = RefineConfig(silhouette_retries=retries)
    assert config.silhouette_retry_backoff and config.silhouette_retry_factor == 3
    result, calls = stand_in_rounds(monkeypatch, worst, kept, config)
    assert len(calls) == len(boosts) and result.casts == returned
    assert result.report.get("silhouette_round", 0) == returned
    assert result.report.get("silhouette_rounds_ended") == ended  # with one round the report has no rounds
    np.testing.assert_allclose(np.array(calls), [[b, 1, 1, 1] for b in boosts], rtol=1e-12)


@pytest.mark.parametrize("with_reach, pushed, without_reach, returned", [
    # the 20-view 128x96 test scene 17: short with the reach, every view on the target without it
    ([0.9766, 0.9777, 0.9794], 5, [0.9749, 0.9803], 4),
    # short without it too: the rounds with it stand
    ([0.9766, 0.9777, 0.9794], 5, [0.9749, 0.9775, 0.9790], 2),
    ([0.9766, 0.9777, 0.9794], 0, None, 2),  # no rim pushed: nothing to run again
    ([0.975, 0.9815], 5, None, 1),  # the target met with the reach (the 20-view scene 0)
])
def test_rounds_left_short_after_pushing_rims_out_run_again_without_the_reach(monkeypatch, with_reach, pushed,
                                                                               without_reach, returned):
    """`silhouette_rounds_without_reach`, the rounds' bookkeeping alone over stand-in rounds (as above):
    where the rounds end short and a round pushed rims out (`outward_reach`), the rounds run again
    without the reach, and the best of those is returned only where every view meets the target."""
    import lookingglass.refine as refine

    V, calls = 4, []
    config = RefineConfig(input_carve=False)
    assert config.silhouette_rounds_without_reach and config.outward_reach

    def one_round(mesh, hull, masks, cameras, config, weights, boost, capture, normals, start):
        calls.append(config.outward_reach)
        worst = (with_reach if config.outward_reach else without_reach)[calls.count(config.outward_reach) - 1]
        return SimpleNamespace(report={"kept": "refined", "seconds": 1.0, "rims_pushed": pushed}, casts=worst)

    monkeypatch.setattr(refine, "_refine_once", one_round)
    monkeypatch.setattr(refine, "cast_iou", lambda casts, masks: np.array([casts, 0.99, 0.99, 0.99]))
    result = refine_pass(None, SimpleNamespace(view_coverage=np.ones(V)), np.zeros((V, 2, 2), bool), None, config)
    assert calls == [True] * len(with_reach) + [False] * len(without_reach or [])
    rounds = result.report["silhouette_rounds"]
    assert result.report["silhouette_round"] == returned
    assert result.casts == rounds[returned]["worst_iou"]
    assert [r.get("outward_reach", True) for r in rounds] == calls


@pytest.mark.parametrize("kept, worst, passes, returned, views", [
    (["refined", "refined"], [0.981, 0.982], 2, 1, 10),
    # from extra_pass_views (20) views on, one pass more
    (["refined", "refined", "refined"], [0.981, 0.982, 0.983], 3, 2, 20),
    (["refined", "refined", "input"], [0.981, 0.982, 0.983], 3, 1, 20),
    (["refined", "input"], [0.981, 0.982], 2, 0, 10),  # the second pass keeps its input: the first pass's mesh
    (["input"], [0.981], 3, None, 10),  # the first keeps its input: no more passes (the same input, the same pass)
    (["refined", "refined", "input"], [0.981, 0.982, 0.983], 3, 1, 10),
    (["refined"], [0.981], 1, 0, 10),
    # within the keep check's tolerance, but off the target the first pass met: not taken
    (["refined", "refined"], [0.981, 0.9795], 2, 0, 10),
    (["refined", "refined"], [0.975, 0.974], 2, 1, 10),  # short before too: the keep check decides
])
def test_each_pass_starts_from_the_mesh_the_pass_before_kept(monkeypatch, kept, worst, passes, returned, views):
    """`passes`, the bookkeeping alone over stand-in passes: each pass refines what the one before kept,
    in one silhouette round at the pull of the round the pass before returned where that pass fell short of
    the target, the passes stop at one that
    keeps its input or takes the worst view below the target the pass before met, and the report gives
    the first input's measures beside the returned mesh's, and each pass's."""
    import lookingglass.refine as refine
    from lookingglass.refine import RefineResult

    calls = []

    def one_pass(mesh, hull, masks, cameras, config, view_coverage, capture, normals, view_names, warn=True,
                 seed=None):
        i = len(calls)
        calls.append((mesh, warn))
        # a later pass starts from what the pass before kept and measured: not cut to the hull again
        assert config.input_carve == (i == 0) and (seed is None) == (i == 0)
        assert seed is None or seed["input_casts"] == i - 1
        # after a pass whose rounds fell short of the target, one round (short_pass_rounds)
        short = i > 0 and worst[i - 1] < 0.98
        assert (config.silhouette_retries, config.silhouette_round_without_normals,
                config.silhouette_rounds_without_reach) == ((0, False, False) if short else (2, True, True))
        # pulling each view as hard as the round the pass before returned
        assert (seed or {}).get("boost", np.ones(2)).tolist() == ([3.0, 1.0] if short else [1.0, 1.0])
        report = {"kept": kept[i], "silhouette_rounds": [{"boost": [1.0, 1.0]}, {"boost": [3.0, 1.0]}],
                  "silhouette_round": 1, "terms_before": {"smooth": i}, "silhouette_iou_before": [i / 10, 1.0],
                  "silhouette_iou_mean": [i / 10, 0.99], "silhouette_iou_after": [worst[i], 0.0],
                  "rerender_error": [0.2 - i / 100, 0.19 - i / 100], "seconds": 1.0,
                  "rerender_error_views": {"input": [i], "refined": [i + 0.5]}}
        # the second view has weight 0 (its mask disagrees with the others): not counted
        return RefineResult(f"mesh {i}" if kept[i] == "refined" else mesh, f"mesh {i}", report, np.array([1.0, 0.0]),
                            i)

    monkeypatch.setattr(refine, "refine_pass", one_pass)
    config = RefineConfig(passes=passes - (views >= 20))  # passes: how many the stage may run
    assert config.extra_pass_views == 20
    result = refine_surface("input", None, np.zeros((views, 1, 1), bool), None, config)
    assert calls == [("input", True)] + [(f"mesh {i}", False) for i in range(len(calls) - 1)]
    stops = [i for i in range(len(kept)) if kept[i] == "input" or (i and worst[i] < 0.98 <= worst[i - 1])]
    assert len(calls) == min(passes, stops[0] + 1 if stops else passes)
    assert result.mesh == ("input" if returned is None else f"mesh {returned}")
    report = result.report
    assert report["kept"] == ("input" if returned is None else "refined")
    # every report says what each pass kept, a single pass's too
    assert [p["kept"] for p in report["passes"]] == [k if i not in stops else "input"
                                                     for i, k in enumerate(kept[:len(calls)])]
    assert [p["rounds"] for p in report["passes"]] == [2] * len(calls)
    assert report["silhouette_iou_before"] == [0.0, 1.0] and report["terms_before"] == {"smooth": 0}
    shown = returned or 0  # the pass whose mesh is returned, or the first where none keeps its refined mesh
    assert report["rerender_error"] == [0.2, 0.19 - shown / 100]
    assert report["rerender_error_views"] == {"input": [0], "refined": [shown + 0.5]}
    assert report["silhouette_iou_after"] == [worst[shown], 0.0]


def test_a_view_with_a_stray_blob_is_down_weighted_and_named(scene):
    gt, cameras, masks, hull = scene
    bad = masks.copy()
    yy, xx = np.mgrid[:masks.shape[1], :masks.shape[2]]
    ys, xs = np.nonzero(masks[4])
    corner = (20, 20) if xs.mean() > 160 else (20, 300)  # far from the object
    blob = (yy - corner[0] - 20) ** 2 + (xx - corner[1]) ** 2 < 18 ** 2
    assert not (blob & masks[4]).any()
    bad[4] |= blob
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        hull_bad = carve_visual_hull(bad, cameras, HullConfig(resolution=64, num_threads=1))
        result = refine_surface(lumpy_shrunken(gt), hull_bad, bad, cameras, CONFIG,
                                view_names=[f"masks/{v:02d}.png" for v in range(len(bad))])
    named = [str(w.message) for w in caught if str(w.message).startswith("refine:")]
    assert len(named) == 1 and "view(s) 4 (masks/04.png, weight" in named[0], named
    weights = result.view_weights
    assert weights[4] < 0.7 and np.all(np.delete(weights, 4) == 1), weights
    assert result.report["down_weighted_views"] == [4]
    assert "silhouette_rounds" not in result.report  # a disagreeing view's mask is not pushed harder
    # the other views are still explained, and the blob did not drag the mesh out to it
    iou = silhouette_iou(result.mesh, cameras, masks)
    assert np.delete(iou, 4).min() >= 0.98 and iou[4] >= 0.98, iou
    assert not (object_masks(result.mesh, cameras.select([4]))[0] & blob).any()


def test_a_good_input_is_not_made_worse(scene):
    gt, cameras, masks, hull = scene
    good = gt.copy()
    result = refine_surface(good, hull, masks, cameras, CONFIG)
    iou_in = silhouette_iou(good, cameras, masks)
    iou_out = silhouette_iou(result.mesh, cameras, masks)
    assert iou_out.mean() >= iou_in.mean() - 1e-4 and iou_out.min() >= iou_in.min() - CONFIG.keep_tolerance
    if result.report["kept"] == "input":
        assert result.mesh is good and result.report["kept_why"]
    else:
        assert shape_metrics(result.mesh, gt)["cd"] < 2.5  # the sampling floor of the metric is ~2


def five_view_scene(gt: trimesh.Trimesh):
    """`gt` seen by a 5-view paper rig at 320x240: the cameras, the masks and their visual hull. 80
    voxels: a carved mesh lies inside the hull, so no view's IoU beats the hull's own, and 80 put the
    slotted bar's worst view at 0.989 (64 voxels: 0.9875, leaving the carve's worst view at 0.9799
    or 0.982 by machine)."""
    cameras = paper_rig(5, rng=3, width=320, height=240)
    masks = object_masks(gt, cameras, samples_per_axis=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hull = carve_visual_hull(masks, cameras, HullConfig(resolution=80, num_threads=1))
    return cameras, masks, hull


def test_slots_the_surface_filled_are_carved_back_by_the_hull():
    """A bar with three slots 0.1 wide (a key's teeth), 5 views: started from the bar with the slots
    filled (what the surface stage gives a key), the silhouette pull cannot open them (it pulls each
    vertex toward the nearest mask boundary, the fairing holds the slot's floor), and one view's
    silhouette spills ~4% of its mask into them; intersected with the visual hull, which the masks
    carved, the slots open. The carve is tried only where a silhouette spills and kept only where
    the masks say it is better."""
    tilt = trimesh.transformations.rotation_matrix(0.3, [1, 0.2, 0])
    bar = trimesh.creation.box([1.4, 0.5, 0.3])
    slots = [trimesh.creation.box([0.1, 0.3, 0.5], trimesh.transformations.translation_matrix([x, 0.15, 0]))
             for x in (-0.4, -0.1, 0.2)]
    gt = bar.difference(slots[0].union(slots[1]).union(slots[2]), engine="manifold")
    gt.apply_transform(tilt)
    filled = bar.subdivide_to_size(0.05)
    filled.apply_transform(tilt)
    cameras, masks, hull = five_view_scene(gt)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = refine_surface(filled, hull, masks, cameras, dataclasses.replace(CONFIG, hull_carve=False,
                                                                                 input_carve=False))
    assert plain.report["kept"] == "refined" and "hull_carve" not in plain.report and "input_carve" not in plain.report
    cast, weights = object_masks(plain.mesh, cameras), np.ones(5)
    carved, cast_carved, report = carve_by_hull(plain.mesh, hull.mesh, cameras, masks, cast, weights, CONFIG)
    assert report["tried"] and report["outside_share_max"] > 0.02 and report["kept"], report
    assert carved.is_watertight and np.array_equal(cast_carved, object_masks(carved, cameras))
    iou_plain, iou_carved = silhouette_iou(plain.mesh, cameras, masks), silhouette_iou(carved, cameras, masks)
    # measured (80 voxels): worst view 0.957 -> 0.986
    assert iou_plain.min() < 0.97 and iou_carved.min() >= 0.98, (iou_plain, iou_carved)
    # closer to the bar (measured: CD 9.94 -> 9.36)
    assert shape_metrics(carved, gt)["cd"] < 0.97 * shape_metrics(plain.mesh, gt)["cd"]
    # the report's IoU is the carved mesh's
    assert report["iou_mean"][1] == pytest.approx(iou_carved.mean(), abs=1e-4)
    assert "crumbs_dropped" not in report
    # the photos can refuse it (`masks_better_rerender_tolerance`): kept where the carved mesh explains them no worse,
    # refused where far worse (stand-ins for the re-rendering error: the volume's distance to the bar's, which
    # the open slots bring closer, and to the filled mesh's)
    filled_volume, bar_volume = plain.mesh.volume, gt.volume
    assert abs(carved.volume - bar_volume) < 0.97 * abs(filled_volume - bar_volume)  # measured: 0.93 x
    closer = carve_by_hull(plain.mesh, hull.mesh, cameras, masks, cast, weights, CONFIG,
                           lambda m: abs(m.volume - bar_volume))
    assert closer[0] is not None and closer[2]["kept"] and closer[2]["rerender_error"][1] < closer[2]["rerender_error"][0]
    farther = carve_by_hull(plain.mesh, hull.mesh, cameras, masks, cast, weights, CONFIG,
                            lambda m: abs(m.volume - filled_volume) + 1e-3)
    assert farther[0] is None and not farther[2]["kept"] and farther[2]["why"] == "it re-renders the photos worse"
    assert CONFIG.masks_better_rerender_tolerance == 0.05  # a few percent worse is what a carve that mends the mesh may cost
    for worse, kept in ((1.04, True), (1.06, False)):
        _, _, report = carve_by_hull(plain.mesh, hull.mesh, cameras, masks, cast, weights, CONFIG,
                                     lambda m: 1.0 if m is plain.mesh else worse)
        assert report["kept"] is kept, (worse, report)
    # a speck grazing the hull from outside leaves no crumb in the carve
    depth = trimesh.proximity.signed_distance(plain.mesh, hull.mesh.vertices)  # hull corners far out of the mesh
    assert depth.min() < -0.02  # the speck lies out of the mesh
    corner = hull.mesh.vertices[np.argmin(depth)]
    speck = trimesh.creation.icosphere(subdivisions=2, radius=0.01).apply_translation(corner)
    specked, _, report = carve_by_hull(trimesh.util.concatenate([plain.mesh, speck]), hull.mesh, cameras, masks, cast,
                                       weights, CONFIG)
    assert report["kept"] and report["crumbs_dropped"] == 1 and specked.body_count == 1, report
    assert specked.volume == pytest.approx(carved.volume, rel=1e-6)
    # not tried where nothing spills; not kept where the hull falls short of the masks (here: shrunk)
    assert carve_by_hull(gt, hull.mesh, cameras, masks, masks, weights, CONFIG)[2] == {
        "outside_share_max": 0.0, "tried": False}
    small = hull.mesh.copy()
    small.vertices = small.vertices.mean(axis=0) + 0.95 * (small.vertices - small.vertices.mean(axis=0))
    refused = carve_by_hull(plain.mesh, small, cameras, masks, cast, weights, CONFIG)
    assert refused[0] is None and refused[2]["tried"] and not refused[2]["kept"], refused[2]


def test_a_web_across_a_hole_is_cut_before_refining():
    """A ring whose hole the surface stage spanned with a web (Poisson closing what PNet's points leave
    thin; the 5-view test scene 55), 5 views at 320x240. Refined as it is, the silhouette pull drags
    the ring's rim toward the web's spill and the keep check refuses the result; the hull carve after
    refining cuts the web but from there the same refusal holds. Cut to the hull first (`input_carve`,
    by the carve's own rule), the rims start free and the refined ring lies at the metric's sampling
    floor with every view's IoU at the hull's."""
    tilt = trimesh.transformations.rotation_matrix(0.5, [1, 0.3, 0])
    gt = trimesh.creation.torus(major_radius=0.6, minor_radius=0.15, major_sections=64, minor_sections=24)
    web = trimesh.creation.cylinder(radius=0.5, height=0.08, sections=64).apply_translation([0.25, 0, 0])
    webbed = gt.union(web, engine="manifold")
    gt.apply_transform(tilt)
    webbed.apply_transform(tilt)
    cameras, masks, hull = five_view_scene(gt)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        after_only = refine_surface(webbed, hull, masks, cameras, dataclasses.replace(CONFIG, input_carve=False))
        cut_first = refine_surface(webbed, hull, masks, cameras, CONFIG)
    assert CONFIG.input_carve and "input_carve" not in after_only.report
    # measured: the webbed ring's worst view 0.758, kept as it is (CD 81)
    assert after_only.report["kept"] == "input" and silhouette_iou(after_only.mesh, cameras, masks).min() < 0.8
    report = cut_first.report["input_carve"]
    assert report["tried"] and report["outside_share_max"] > 0.1 and report["kept"], report
    # the keep check weighed the refined ring against the cut input: the report's silhouettes before are its
    cut, _, _ = carve_by_hull(webbed, hull.mesh, cameras, masks, object_masks(webbed, cameras), np.ones(5), CONFIG)
    assert cut_first.report["silhouette_iou_before"] == pytest.approx(silhouette_iou(cut, cameras, masks), abs=1e-4)
    assert cut_first.report["kept"] == "refined"
    iou = silhouette_iou(cut_first.mesh, cameras, masks)
    # measured: CD 1.51 (a ring's own sampling floor is ~1-2 at 20 000 samples), worst view 0.997 (the hull's 0.997)
    assert shape_metrics(cut_first.mesh, gt)["cd"] < 3.0
    assert iou.min() >= silhouette_iou(hull.mesh, cameras, masks).min() - 0.01, iou
    # nothing spills from the refined ring: as an input it is left as it is
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = refine_surface(cut_first.mesh, hull, masks, cameras, CONFIG)
    assert not again.report["input_carve"]["tried"]
    assert again.report["input_carve"]["outside_share_max"] <= CONFIG.carve_outside_share


def ring_with_tube(tube) -> trimesh.Trimesh:
    """A ring in the xy plane whose hole is a circle of radius 0.45 and whose tube radius is tube(phi)
    (phi: the angle around the ring): where the tube is thinner, the ring is narrower on the outside."""
    phi, theta = np.meshgrid(np.linspace(0, 2 * np.pi, 128, endpoint=False),
                             np.linspace(0, 2 * np.pi, 24, endpoint=False), indexing="ij")
    r = tube(phi)
    centre = 0.45 + r
    vertices = np.stack([(centre + r * np.cos(theta)) * np.cos(phi), (centre + r * np.cos(theta)) * np.sin(phi),
                         r * np.sin(theta)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(128), np.arange(24), indexing="ij")
    a, b = i * 24 + j, (i + 1) % 128 * 24 + j
    c, d = (i + 1) % 128 * 24 + (j + 1) % 24, i * 24 + (j + 1) % 24
    mesh = trimesh.Trimesh(vertices, np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3),
                                                     np.stack([a, c, d], -1).reshape(-1, 3)]), process=False)
    mesh.fix_normals()
    return mesh


def test_a_rim_whose_nearest_boundary_lies_behind_it_is_pushed_out():
    """A ring whose surface is less than half as thick as its masks over two fifths of its round, on the
    outside (the 5-view test scene 55's handle): there each outer rim vertex is nearer the hole's
    boundary behind it than the mask's outer boundary ahead, so the pull to the nearest boundary holds
    it where it is or drags it inward. Where the field deepens outward, marching along the
    silhouette's outward direction (`outward_reach`) finds where the mask ends, and the rims are pushed
    there. Measured on the refined mesh whether kept or not: stretched to twice its girth, the smooth
    input's Laplacian grows, and the keep check's roughness measure refuses both meshes."""
    tilt = trimesh.transformations.rotation_matrix(0.5, [1, 0.3, 0])
    gt = ring_with_tube(lambda phi: np.full_like(phi, 0.15)).apply_transform(tilt)

    def dip(phi):
        away = np.clip(np.abs(np.angle(np.exp(1j * phi))) / 2, 0, 1)  # 0 at phi = 0, 1 from |phi| = 2 on
        return 0.15 - 0.09 * np.clip(1.2 * np.cos(away * np.pi / 2), 0, 1)

    thin = lumpy_shrunken(ring_with_tube(dip), scale=1.0).apply_transform(tilt)
    cameras, masks, hull = five_view_scene(gt)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        nearest = refine_surface(thin, hull, masks, cameras, dataclasses.replace(CONFIG, outward_reach=False))
        pushed = refine_surface(thin, hull, masks, cameras, CONFIG)
    assert CONFIG.outward_reach
    assert nearest.report["constraints_first_last"][0]["pushed"] == 0
    assert pushed.report["constraints_first_last"][0]["pushed"] > 0
    worst_nearest = min(nearest.report["silhouette_iou_after"])
    worst_pushed = min(pushed.report["silhouette_iou_after"])
    # measured: the input's worst view 0.602; pulled to the nearest boundary 0.764, pushed out 0.962
    assert worst_nearest < 0.85 and worst_pushed > 0.94, (worst_nearest, worst_pushed)
    # measured: CD 71.8 (the input), 38.7 (the nearest boundary), 5.7 (pushed out)
    cd_nearest, cd_pushed = shape_metrics(nearest.refined, gt)["cd"], shape_metrics(pushed.refined, gt)["cd"]
    assert cd_pushed < 0.3 * cd_nearest, (cd_nearest, cd_pushed)


def test_an_input_made_worse_is_rejected(scene):
    """The keep check itself: a refinement that cannot help (no iterations, only the remeshing)
    of a mesh already on the masks must not replace it when it does not improve the measures."""
    gt, cameras, masks, hull = scene
    coarse = dataclasses.replace(CONFIG, edge_length=0.2, iterations=0)  # a far coarser copy
    result = refine_surface(gt, hull, masks, cameras, coarse)
    assert result.report["kept"] == "input" and result.mesh is gt
    assert "silhouette IoU" in result.report["kept_why"]


def test_the_keep_check_weighs_a_small_iou_loss_against_the_photos():
    """The mean IoU may fall by up to keep_tolerance only where the refined mesh re-renders the
    photos better (by more than the re-rendering's 1% tolerance); otherwise it is strict, and the
    worst view, the roughness and fold-overs are checked as before."""
    tol, w = 0.002, np.ones(4)
    iou_in = np.array([0.990, 0.992, 0.994, 0.996])
    iou_out = iou_in - 0.001  # every view 0.001 lower: within tol
    rough = (1.0, 0.5)
    assert worse_measures(iou_in, iou_in, w, rough, 0, None, tol) == []
    [why] = worse_measures(iou_in, iou_out, w, rough, 0, None, tol)  # no photos: strict
    assert why.startswith("mean silhouette IoU")
    assert worse_measures(iou_in, iou_out, w, rough, 0, (0.10, 0.08), tol) == []  # photos better: kept
    [why] = worse_measures(iou_in, iou_out, w, rough, 0, (0.10, 0.0995), tol)  # within the 1% tolerance: strict
    assert why.startswith("mean silhouette IoU")
    # the mean 0.003 lower (beyond tol), the worst view unchanged: refused for the mean alone
    [why] = worse_measures(iou_in, iou_in - np.array([0, 0.004, 0.004, 0.004]), w, rough, 0, (0.10, 0.08), tol)
    assert why.startswith("mean silhouette IoU")
    both = worse_measures(iou_in, iou_out, w, rough, 0, (0.10, 0.102), tol)  # photos worse by 2%
    assert [b.split(" ")[0] for b in both] == ["re-rendering", "mean"], both
    # a zero-weight view counts in neither the mean nor the worst view
    down = np.array([1.0, 1.0, 1.0, 0.0])
    assert worse_measures(iou_in, np.append(iou_in[:3], 0.5), down, rough, 0, None, tol) == []
    assert worse_measures(iou_in, iou_in, w, (1.0, 1.01), 2, None, tol) == ["roughness 1 -> 1.01", "2 fold-over(s)"]


@pytest.mark.parametrize("kept, term_kept, views, passes, term_passes, passes_run", [
    (["refined"] * 3, [True, True, True], 10, 2, 1, 3),  # the second pass kept its normal term: one more
    (["refined"] * 3, [True, False, True], 10, 2, 1, 2),  # its term dropped: the next net sees about the same mesh
    (["refined", "input", "refined"], [True, True, True], 10, 2, 1, 2),  # it kept its input: the passes end
    (["refined"] * 3, [True, True, True], 10, 2, 0, 2),  # off (the default): passes alone decides
    (["refined"] * 3, [True, True, True], 10, 1, 0, 1),  # one pass asked for, one run
    (["refined"] * 4, [True, True, True, True], 10, 1, 2, 3),  # at most term_passes more
    (["refined"] * 4, [True, True, False, True], 20, 2, 1, 3),  # 20 views: three passes, the third's term dropped
    (["refined"] * 4, [True, True, True, True], 20, 2, 1, 4),
])
def test_a_pass_that_kept_its_normal_term_earns_one_more(monkeypatch, kept, term_kept, views, passes, term_passes,
                                                         passes_run):
    """`term_passes`: past `passes` (and the extra pass from 20 views), up to term_passes more passes
    run, each while the pass before kept its refined mesh and its normal term's steps."""
    import lookingglass.refine as refine
    from lookingglass.refine import RefineResult

    calls = []

    def one_pass(mesh, hull, masks, cameras, config, view_coverage, capture, normals, view_names, warn=True,
                 seed=None):
        i = len(calls)
        calls.append(mesh)
        report = {"kept": kept[i], "normal_term": {"kept": term_kept[i]}, "terms_before": {},
                  "silhouette_iou_before": [0.99], "silhouette_iou_mean": [0.99, 0.99],
                  "silhouette_iou_after": [0.99], "seconds": 1.0}
        return RefineResult(f"mesh {i}" if kept[i] == "refined" else mesh, f"mesh {i}", report, np.ones(1), i)

    monkeypatch.setattr(refine, "refine_pass", one_pass)
    result = refine_surface("input", None, np.zeros((views, 1, 1), bool), None,
                            RefineConfig(passes=passes, term_passes=term_passes))
    assert len(calls) == passes_run
    assert [p["normal_term_kept"] for p in result.report["passes"]] == term_kept[:passes_run]


def test_the_keep_check_passes_over_a_mean_iou_fall_within_its_noise_where_the_photos_are_no_worse():
    """A later pass refused for a mean IoU 0.0001 lower with a better re-rendering (val240v20's finned
    body, session 89): the mean may fall by up to keep_iou_noise where the re-rendering is no worse
    at all; a fall beyond it, or any worse re-rendering, is judged as before."""
    tol, noise, w, rough = 0.002, 0.0005, np.ones(4), (1.0, 0.5)
    iou_in = np.array([0.990, 0.992, 0.994, 0.996])
    small, large = iou_in - 0.0003, iou_in - 0.0008
    assert worse_measures(iou_in, small, w, rough, 0, (0.2104, 0.2097), tol, iou_noise=noise) == []
    assert worse_measures(iou_in, small, w, rough, 0, (0.2104, 0.2104), tol, iou_noise=noise) == []  # equal
    [why] = worse_measures(iou_in, small, w, rough, 0, (0.2104, 0.2105), tol, iou_noise=noise)  # a little worse
    assert why.startswith("mean silhouette IoU")
    [why] = worse_measures(iou_in, large, w, rough, 0, (0.2104, 0.2097), tol, iou_noise=noise)  # beyond the noise
    assert why.startswith("mean silhouette IoU")
    [why] = worse_measures(iou_in, small, w, rough, 0, None, tol, iou_noise=noise)  # no photos: strict
    assert why.startswith("mean silhouette IoU")
    [why] = worse_measures(iou_in, small, w, rough, 0, (0.2104, 0.2097), tol)  # the noise 0 by default: strict
    assert why.startswith("mean silhouette IoU")


def test_the_keep_check_lets_the_photos_be_a_little_worse_where_the_masks_are_clearly_better():
    """Where the worst view and the mean IoU both rise by more than 0.01 (MASKS_CLEARLY_BETTER), the
    re-rendering may be worse by up to masks_better_rerender_tolerance (5%) instead of 1%: the 5-view
    test scene 35's refined mesh (worst view 0.939 -> 0.987, CD 15.31 -> 13.82) was refused for +1.4%."""
    from lookingglass.refine import MASKS_CLEARLY_BETTER, RERENDER_TOLERANCE

    tol, w, rough = 0.002, np.ones(4), (1.0, 0.5)
    assert RERENDER_TOLERANCE == 0.01 and MASKS_CLEARLY_BETTER == 0.01
    iou_in = np.array([0.939, 0.95, 0.94, 0.946])  # scene 35's figures, roughly
    iou_out = np.array([0.987, 0.99, 0.989, 0.99])
    assert worse_measures(iou_in, iou_out, w, rough, 0, (0.1548, 0.1569), tol) == []
    assert worse_measures(iou_in, iou_out, w, rough, 0, (0.100, 0.104), tol) == []
    [why] = worse_measures(iou_in, iou_out, w, rough, 0, (0.100, 0.106), tol)  # beyond 5%
    assert why.startswith("re-rendering error")
    [why] = worse_measures(iou_in, iou_out, w, rough, 0, (0.100, 0.104), tol, masks_better_tolerance=0.01)
    assert why.startswith("re-rendering error")
    # the worst view up by less than 0.01 (the mean by more): 1% again
    barely = iou_in + np.array([0.009, 0.05, 0.05, 0.05])
    assert barely.min() - iou_in.min() < MASKS_CLEARLY_BETTER < barely.mean() - iou_in.mean()
    [why] = worse_measures(iou_in, barely, w, rough, 0, (0.100, 0.104), tol)
    assert why.startswith("re-rendering error")
    # the mean up by less than 0.01 (the worst view by more): 1% again
    one_short, spread = np.array([0.939, 0.99, 0.99, 0.99]), np.array([0.99, 0.975, 0.975, 0.975])
    assert spread.min() - one_short.min() > MASKS_CLEARLY_BETTER > spread.mean() - one_short.mean()
    [why] = worse_measures(one_short, spread, w, rough, 0, (0.100, 0.104), tol)
    assert why.startswith("re-rendering error")


def test_the_stage_is_configured():
    assert STAGES[-1] == "refine" and PipelineConfig().stop_after == "refine"
    assert isinstance(PipelineConfig().refine, RefineConfig)
    with pytest.raises(ConfigError, match="edge_length"):
        RefineConfig(edge_length=0)
    with pytest.raises(ConfigError, match="view_coverage_zero"):
        RefineConfig(view_coverage_zero=0.99, view_coverage_full=0.9)


@pytest.fixture(scope="module")
def capture(scene):
    """The ellipsoid rendered as glass by the renderer under a smooth synthetic map: the photos."""
    gt, cameras, masks, hull = scene
    u = torch.linspace(0, 1, 64)
    v = torch.linspace(0, 1, 32)[:, None]
    env = torch.stack([0.2 + u.expand(32, -1), 0.2 + v.expand(-1, 64), 0.5 + 0.4 * torch.sin(9 * u) * v], -1)
    small = cameras.with_resolution(160, 120)
    photos = render_views(gt, EnvironmentMap(env), small, RenderConfig(samples_per_axis=2)).image
    photos = torch.nn.functional.interpolate(photos.permute(0, 3, 1, 2), size=masks.shape[1:], mode="bilinear")
    return SimpleNamespace(images=photos.permute(0, 2, 3, 1).numpy(), masks=masks, envmap=env.numpy(),
                           cameras=cameras, ior=IOR_GLASS)


def normal_stage(capture, hull, n1, n2, error, predicted_gain=None) -> SimpleNamespace:
    """What the normal stage hands the refine stage (`NormalStageResult`'s inputs and maps), at
    80x60, with the given normal maps (a function of the inputs' cameras), rendering-error maps
    and, when given, the gain head's estimate (degrees, the same at every pixel and hit)."""
    x = NormalInputs.from_capture(capture.images, capture.masks, capture.envmap, capture.cameras, capture.ior,
                                  hull.mesh, 80, 60, 32)
    n1, n2 = n1(x.cameras), n2(x.cameras)
    head = None if predicted_gain is None else torch.full((*x.mask.shape, 2), float(predicted_gain))
    maps = NormalMaps(x.cameras, n1, n2, torch.full(x.mask.shape, float(error)), torch.zeros_like(x.mask), x.mask,
                      predicted_gain=head)
    return SimpleNamespace(inputs=x, maps=maps)


def test_the_normal_term_follows_what_the_gain_head_vouches_for(scene, capture):
    """With the true normals as the network's prediction and a predicted gain of 5 degrees (above
    the 2-degree bar) every pixel pulls: the term removes the ridges the silhouette pulls leave
    (CDN-mean against the ellipsoid falls well below the silhouette-only result's) and its loss
    falls; with a predicted gain of -5 degrees (the mesh's normals said to be the better) nothing is
    trusted and nothing moves; a net without a gain head is not followed at all (the term was
    measured to make meshes worse without it), and the report says so."""
    gt, cameras, masks, hull = scene
    start = lumpy_shrunken(gt)
    base_config = dataclasses.replace(CONFIG, rerender_width=0)
    base = refine_surface(start, hull, masks, cameras, base_config).refined
    truth = lambda c: trace_two_bounce(gt, c, ior=IOR_GLASS)  # noqa: E731
    n1, n2 = (lambda c: truth(c).normal1), (lambda c: truth(c).normal2)  # noqa: E731
    # the second pass, as `reconstruct` runs it: the net fed the mesh the silhouette iterations left
    fed = lambda gain: lambda mesh: normal_stage(capture, SimpleNamespace(mesh=mesh), n1, n2, 0.0, gain)  # noqa: E731
    result = refine_surface(start, hull, masks, cameras, base_config, normals=fed(5.0))
    term = result.report["normal_term"]
    assert term["trusted_share"] > 0.9 and term["kept"]  # of the masks' pixels
    assert len(term["loss"]) == base_config.normal_iterations + 1 and term["loss"][-1] < 0.3 * term["loss"][0]
    cdn_base, cdn = (shape_metrics(m, gt)["cdn_mean"] for m in (base, result.refined))
    assert cdn < 0.7 * cdn_base, (cdn_base, cdn)
    assert min(result.report["silhouette_iou_after"]) > 0.97
    # `reconstruct`'s own second pass with a net that has no gain head (one trained without) does
    # not run the net at all
    headless = second_pass(capture, SimpleNamespace(net=SimpleNamespace(cfg=SimpleNamespace(gain_head=False))))
    # (what follows skips the term, whatever the iterations before it: 3 of them keep the test fast)
    short = dataclasses.replace(base_config, iterations=3)
    short_base = refine_surface(start, hull, masks, cameras, short).refined
    for stage, said in ((fed(-5.0), {"trusted_share": 0.0}),
                        (fed(None), {"skipped": "the normal net has no gain head"}),
                        (headless, {"skipped": "the normal net has no gain head"})):
        result = refine_surface(start, hull, masks, cameras, short, normals=stage)
        assert result.report["normal_term"] == said
        np.testing.assert_allclose(result.refined.vertices, short_base.vertices, atol=1e-9)


def test_the_second_pass_feeds_the_network_the_mesh_and_keeps_what_explains_the_photos(scene, capture):
    """`normals` as a function (what `reconstruct` passes): it is called once, with the mesh the
    silhouette iterations left (the refined mesh's triangles), and what it returns is the target.
    On a mesh that is already right (the ellipsoid itself), a target the photos contradict (the
    true normals turned by 25 degrees, vouched for by the gain head) moves the mesh, and the
    re-rendering against the photos drops the move: the result is the silhouette-only mesh, and
    the report gives both re-rendering errors."""
    gt, cameras, masks, hull = scene
    start = gt
    config = dataclasses.replace(CONFIG, rerender_width=80)
    base = refine_surface(start, hull, masks, cameras, config, capture=capture)
    truth = lambda c: trace_two_bounce(gt, c, ior=IOR_GLASS)  # noqa: E731
    c, s = np.cos(np.radians(25)), np.sin(np.radians(25))
    tilt = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    fed = []

    def turned_truth(mesh):
        fed.append(mesh)
        tilted = lambda n: n @ tilt.to(n.dtype).T  # noqa: E731
        return normal_stage(capture, SimpleNamespace(mesh=mesh), lambda c: tilted(truth(c).normal1),
                            lambda c: tilted(truth(c).normal2), 0.0, 5.0)

    result = refine_surface(start, hull, masks, cameras, config, capture=capture, normals=turned_truth)
    assert len(fed) == 1 and len(fed[0].faces) == result.report["faces"]
    term = result.report["normal_term"]
    assert term["trusted_share"] > 0.5 and term["loss"][-1] < term["loss"][0]
    e_without, e_with = term["rerender_error"]
    assert not term["kept"] and e_with > e_without * 1.01, term
    np.testing.assert_allclose(result.refined.vertices, base.refined.vertices, atol=1e-9)


def test_each_pass_feeds_the_network_a_better_mesh(scene, capture):
    """`passes`: a stand-in net that corrects half of what its input gets wrong (its normals halfway
    between those of the mesh it is fed and the truth: a net that improves its input, as the shipped
    ones do by 0.5-0.9 x) gives a second pass a closer target, and the mesh follows: the passes
    converge on the truth, where more steps against the first pass's target would not move it."""
    gt, cameras, masks, hull = scene
    truth = lambda c: trace_two_bounce(gt, c, ior=IOR_GLASS)  # noqa: E731

    def halfway(a, b):
        s = a + b  # a miss (zero) on the fed mesh leaves the truth
        return s / s.norm(dim=-1, keepdim=True).clamp_min(1e-9)

    def half_correcting(mesh):
        fed = lambda c: trace_two_bounce(mesh, c, ior=IOR_GLASS)  # noqa: E731
        return normal_stage(capture, SimpleNamespace(mesh=mesh), lambda c: halfway(fed(c).normal1, truth(c).normal1),
                            lambda c: halfway(fed(c).normal2, truth(c).normal2), 0.0, 5.0)

    start = lumpy_shrunken(gt)
    cdn = []
    for passes in (1, 2):
        config = dataclasses.replace(CONFIG, rerender_width=0, passes=passes)
        result = refine_surface(start, hull, masks, cameras, config, normals=half_correcting)
        cdn.append(shape_metrics(result.mesh, gt)["cdn_mean"])
        assert min(result.report["silhouette_iou_after"]) > 0.99
    assert [p["kept"] for p in result.report["passes"]] == ["refined", "refined"]
    # no re-rendering check here (rerender_width 0): each pass keeps its normal term's steps
    assert [p.get("normal_term_kept") for p in result.report["passes"]] == [True, True]
    assert cdn[1] < 0.8 * cdn[0], cdn  # measured 3.04 -> 1.93 degrees (a third pass: 1.64)


def test_a_round_whose_normal_term_undid_its_pull_is_run_again_without_it(scene, capture, monkeypatch):
    """A round that pulls short views harder (silhouette_retries), whose normal term slides the rims off
    those views' masks, is run once more without the term where the rounds end short, and that run is
    returned; the report names the round and the views. The term here swells the mesh by 3% (~1.5 px at
    320x240: every view below 0.98), where the network's targets would move it a little."""
    import lookingglass.refine as refine

    gt, cameras, masks, hull = scene
    assert list(refine.silhouette_lost(np.array([0.99, 0.985, 0.97, 0.97]), np.array([0.975, 0.99, 0.969, 0.96]),
                                       np.array([True, True, True, True]), CONFIG)) == [0, 3]
    truth = lambda c: trace_two_bounce(gt, c, ior=IOR_GLASS)  # noqa: E731
    fed = lambda mesh: normal_stage(capture, SimpleNamespace(mesh=mesh), lambda c: truth(c).normal1,  # noqa: E731
                                    lambda c: truth(c).normal2, 0.0, 5.0)

    def swelling(x, x0, faces, target, precondition, step, iterations, growth=1.0, conjugate=False):
        centre = x.mean(axis=0)
        return centre + 1.03 * (x - centre), [1.0, 0.5]

    monkeypatch.setattr(refine, "_descend", swelling)
    # a coarser mesh and 4 iterations a round (the test's time); no hull carve: it would cut the swollen rims
    # back to the hull
    config = dataclasses.replace(CONFIG, rerender_width=0, silhouette_retries=1, silhouette_retry_backoff=False,
                                 hull_carve=False, iterations=4, edge_length=0.05)
    result = refine_surface(lumpy_shrunken(gt), hull, masks, cameras, config, normals=fed)
    rounds = result.report["silhouette_rounds"]
    # the first round pulls no view harder; the second pulls every view 3 x and its term undoes that
    assert len(rounds) == 3 and "normal_term_lowered" not in rounds[0], rounds
    assert rounds[1]["boost"] == [3.0] * 10 and rounds[1]["normal_term_lowered"] == list(range(10)), rounds
    assert max(rounds[0]["worst_iou"], rounds[1]["worst_iou"]) < 0.98, rounds
    assert rounds[2]["boost"] == [3.0] * 10 and rounds[2]["normal_term"] == "off (round 1's pull)", rounds
    assert result.report["silhouette_round"] == 2 and "normal_term" not in result.report
    assert min(result.report["silhouette_iou_after"]) == rounds[2]["worst_iou"] >= 0.98


def test_photos_are_checked_and_the_photometric_term_descends(scene, capture):
    """With the photos (the ellipsoid rendered as glass by the renderer), the keep check
    re-renders input and result against them and keeps the one that explains them better; the
    opt-in photometric term lowers its own loss step by step."""
    gt, cameras, masks, hull = scene
    config = dataclasses.replace(CONFIG, photometric_iterations=2, rerender_width=80)
    result = refine_surface(lumpy_shrunken(gt), hull, masks, cameras, config, capture=capture)
    report = result.report
    losses = report["photometric_loss"]
    assert len(losses) == 3 and losses[-1] < losses[0] and all(b <= a for a, b in zip(losses, losses[1:]))
    # The known limit of test_shrunken_lumpy_mesh_is_pulled_onto_the_masks, seen in the photos: the
    # ridges the local pulls leave (CDN-mean 1.7 -> 9.3 degrees) double the re-rendering error
    # (0.016 -> 0.031; the ellipsoid itself scores 0.002), so the input is kept, and said why.
    rr_in, rr_out = report["rerender_error"]
    assert rr_out > 1.5 * rr_in and report["kept"] == "input" and "re-rendering error" in report["kept_why"]
    assert result.rerendering.error.shape == (len(masks),)
    assert abs(result.rerendering.mean_error - rr_in) < 1e-4  # the picture shows the kept mesh


def test_coarse_masks_pull_less():
    """The silhouette weight applies whole from silhouette_width (480) up and falls as a power of the
    width below it (a 128-pixel mask's boundary is 3.75x coarser); the fairing, which those masks then
    hold back less, as a lower power; the defaults give 128-pixel masks the weights measured there
    (0.38 and 14, with the fairing keeping the curvature: session 57). Fewer views than
    silhouette_views pull harder, and on coarse masks fewer than silhouette_views_coarse."""
    from lookingglass.refine import fair_curvature_share, fair_weight, silhouette_weight

    config = RefineConfig(silhouette_weight=2.0, silhouette_width_power=2.0, silhouette_views=10)
    assert silhouette_weight(config, 480) == silhouette_weight(config, 1920) == 2.0
    assert silhouette_weight(config, 128) == pytest.approx(2.0 * (128 / 480) ** 2, rel=1e-12)
    assert silhouette_weight(config, 240) == pytest.approx(0.5, rel=1e-12)
    assert silhouette_weight(dataclasses.replace(config, silhouette_width=0), 64) == 2.0
    assert silhouette_weight(RefineConfig(), 128) == pytest.approx(0.379, rel=0.01)  # measured at 128x96
    assert fair_weight(RefineConfig(), 128) == pytest.approx(14.2, rel=0.01)
    # fewer than silhouette_views (10) views: the weight times 10 / V; more: unchanged
    assert silhouette_weight(config, 480, 5) == pytest.approx(4.0, rel=1e-12)
    assert silhouette_weight(config, 480, 10) == silhouette_weight(config, 480, 20) == 2.0
    assert silhouette_weight(dataclasses.replace(config, silhouette_views=0), 480, 5) == 2.0
    # on coarse masks (the fairing keeps the curvature there) the threshold is silhouette_views_coarse;
    # between, the two factors blend as the fairing does
    coarse = dataclasses.replace(config, silhouette_views=5, silhouette_views_coarse=10)
    assert silhouette_weight(coarse, 480, 5) == 2.0 and silhouette_weight(coarse, 480, 4) == pytest.approx(2.5)
    assert silhouette_weight(coarse, 128, 5) == pytest.approx(2 * silhouette_weight(coarse, 128, 10), rel=1e-12)
    assert silhouette_weight(coarse, 128, 20) == silhouette_weight(coarse, 128, 10)
    share = fair_curvature_share(coarse, 360)
    assert 0 < share < 1 and silhouette_weight(coarse, 360, 5) == pytest.approx(
        (1 + share) * silhouette_weight(coarse, 360, 10), rel=1e-12)
    default = RefineConfig()
    assert fair_weight(default, 480) == fair_weight(default, 1000) == default.fair_weight
    assert fair_weight(default, 240) == pytest.approx(default.fair_weight * 0.5 ** default.fair_width_power, rel=1e-12)


def test_the_descent_step_grows_back_after_a_step_that_fell():
    """`_descend` (the normal and photometric terms): a step that does not lower the loss is halved;
    with `growth` > 1 each step that does is followed by a longer one (at most the first), so one
    rough spot (ray-cast losses are piecewise) does not leave the descent crawling. A uniform shift
    u of a mesh toward a minimum at u = 1, with a bump at u = 0.3 that rejects the first step of
    0.3: growing by 2, the steps after the halved one are 0.3 again."""
    from lookingglass.refine import _descend

    sphere = trimesh.creation.icosphere(subdivisions=2)
    x0, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)

    def loss(x, f, grad):
        u = float((x - x0)[:, 0].mean())
        bump = 10.0 if 0.28 < u < 0.32 else 0.0
        return (u - 1.0) ** 2 + bump, lambda: np.tile([2 * (u - 1.0), 0.0, 0.0], (len(x), 1))

    reached = {}
    for growth in (1.0, 2.0):
        x, losses = _descend(x0.copy(), x0, faces, SimpleNamespace(loss=loss), lambda g: g, 0.3, 4, growth)
        assert all(b < a for a, b in zip(losses, losses[1:])), losses
        reached[growth] = float((x - x0)[:, 0].mean())
    # halving-only meets the bump again at 0.15 + 0.15 and creeps up to it in ever shorter steps
    assert reached[1.0] < 0.3 and reached[2.0] == pytest.approx(0.15 + 3 * 0.3), reached


def test_a_descent_that_cannot_step_reads_its_gradient_again():
    """`_descend` where no step lowers the loss (a mesh at its minimum): every trial is refused, so each
    next step starts from the same vertices and gradient, which `_gradient` computes once and hands out
    again (its backward pass runs only when asked: a second one through the freed graph would raise)."""
    from lookingglass.refine import _descend, _gradient

    sphere = trimesh.creation.icosphere(subdivisions=2)
    x0, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    backward = []

    def loss(x, f, grad):
        t = torch.as_tensor(x).requires_grad_(grad)
        value = ((t - torch.as_tensor(x0)) ** 2).sum()
        if not grad:
            return float(value), None
        backward.append(_gradient(value, t))
        return float(value), backward[-1]

    x, losses = _descend(x0.copy(), x0, faces, SimpleNamespace(loss=loss), lambda g: g, 0.1, 3)
    assert np.array_equal(x, x0) and losses == [0.0] * 4
    first = backward[0]
    assert np.array_equal(first(), np.zeros_like(x0)) and first() is first()


def test_conjugate_directions_stop_the_descent_zig_zagging():
    """`_descend(conjugate=True)` (`RefineConfig.descent_conjugate`): on a stretched quadratic bowl, a
    uniform shift (u, v) of a mesh with the loss (u - 0.3)^2 + 30 (v - 0.1)^2, plain smoothed-gradient
    steps zig-zag across the narrow axis; the Polak-Ribiere+ directions reach a loss over ten times
    lower in the same 12 steps, each step still lowering it."""
    from lookingglass.refine import _descend

    sphere = trimesh.creation.icosphere(subdivisions=2)
    x0, faces = np.asarray(sphere.vertices), np.asarray(sphere.faces)

    def loss(x, f, grad):
        u, v = (x - x0)[:, 0].mean(), (x - x0)[:, 1].mean()
        return (u - 0.3) ** 2 + 30 * (v - 0.1) ** 2, lambda: np.tile([2 * (u - 0.3), 60 * (v - 0.1), 0.0], (len(x), 1))

    final = {}
    for conjugate in (False, True):
        _, losses = _descend(x0.copy(), x0, faces, SimpleNamespace(loss=loss), lambda g: g, 0.2, 12, 2.0, conjugate)
        assert all(b < a for a, b in zip(losses, losses[1:])), losses
        final[conjugate] = losses[-1]
    assert final[True] < final[False] / 10, final


def test_the_linear_solve_solves_the_silhouette_system():
    """`_Solver` (the silhouette solves and the descents' smoothing): with enough CG iterations its
    solution satisfies (M + L^T C L + c I) d = rhs, the system assembled and solved directly here, to 1e-4
    (CG stops at a residual of 1e-5 of the right-hand side's). Capped at 60 iterations (the
    descents' until session 47) it is off by 4% on this 2562-vertex sphere (25% on a 30 000-vertex
    refine mesh: the smooth modes converge last), at 150 by 0.02%."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from lookingglass.refine import _Solver

    sphere = trimesh.creation.icosphere(subdivisions=4)
    N = len(sphere.vertices)
    lap = uniform_laplacian(np.asarray(sphere.faces), N)
    rng = np.random.default_rng(0)
    c_lap = rng.uniform(100, 300, N)
    M = np.zeros((N, 3, 3))
    rows = rng.choice(N, N // 5, replace=False)
    n = rng.normal(size=(len(rows), 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    M[rows] = 20 * n[:, :, None] * n[:, None, :]
    rhs = rng.normal(size=(N, 3))
    # the system over the interleaved coordinates (x0, y0, z0, x1, ...), solved directly (SuperLU)
    system = sp.kron(lap.T @ sp.diags(c_lap) @ lap + 0.1 * sp.identity(N), sp.identity(3)) \
        + sp.block_diag([M[i] for i in range(N)])
    exact = spla.spsolve(sp.csc_matrix(system), rhs.ravel()).reshape(N, 3)
    solver = _Solver(lap, c_lap, 0.1, 60)
    solved = solver.operator(M, 2000)(rhs)
    assert np.linalg.norm(solved - exact) < 1e-4 * np.linalg.norm(exact)
    error = {k: np.linalg.norm(solver.operator(M, k)(rhs) - exact) / np.linalg.norm(exact) for k in (60, 150)}
    assert error[60] > 0.02 and error[150] < 1e-3, error


def test_a_robust_misfit_lets_pixels_the_mesh_cannot_follow_go(scene, capture):
    """`normal_robust`: where the target contradicts itself (here every 5th pixel's normals turned
    by 60 degrees, as where the mesh's ray reaches another sheet than the network's), the plain
    mean follows the wrong pixels too, and their jumps stall the line search; the robust misfit
    (each ray's misfit m as s m / (s + m)) bounds what one ray can add, and the mesh comes out
    much closer to the ellipsoid (CDN-mean) than with the plain mean."""
    gt, cameras, masks, hull = scene
    start = lumpy_shrunken(gt)
    config = dataclasses.replace(CONFIG, rerender_width=0)

    def turned(c, which):
        n = getattr(trace_two_bounce(gt, c, ior=IOR_GLASS), which)
        rows, cols = torch.meshgrid(torch.arange(c.height), torch.arange(c.width), indexing="ij")
        wrong = ((rows + 2 * cols) % 5 == 0)[None, ..., None]
        axis = torch.tensor([0.0, 0.0, 1.0])
        rotated = n * np.cos(np.pi / 3) + torch.cross(axis.expand_as(n), n, dim=-1) * np.sin(np.pi / 3) \
            + axis * (n * axis).sum(-1, keepdim=True) * (1 - np.cos(np.pi / 3))
        return torch.where(wrong, rotated, n)

    fed = lambda mesh: normal_stage(capture, SimpleNamespace(mesh=mesh), lambda c: turned(c, "normal1"),  # noqa: E731
                                    lambda c: turned(c, "normal2"), 0.0, 5.0)
    cdn = {}
    for robust in (0.0, 0.03):
        result = refine_surface(start, hull, masks, cameras, dataclasses.replace(config, normal_robust=robust),
                                normals=fed)
        cdn[robust] = shape_metrics(result.refined, gt)["cdn_mean"]
    # measured: plain 4.48, robust 1.79 (the silhouette iterations alone 6.14)
    assert cdn[0.03] < 0.6 * cdn[0.0], cdn


def test_only_the_plain_fairing_is_weakened_on_thin_parts():
    """fair_vertex_shares: at full-width masks (plain fairing) a vertex's share of the fairing is
    (thickness / fair_thickness)^2 below fair_thickness and 1 above; on coarse masks, where the fairing
    keeps the curvature and does not shrink a thin part, every share is 1; between, the plain part's
    share is weakened only."""
    from lookingglass.refine import fair_curvature_share, fair_vertex_shares

    rod = trimesh.creation.capsule(height=1.0, radius=0.05, count=[16, 16])  # diameter 0.1: half of 0.2
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.4)  # diameter 0.8
    config = RefineConfig(fair_thickness=0.2)
    for mesh, most in ((rod, 0.45), (ball, 1.0)):  # the rod's thickness measures 0.1-0.13 (smoothed): 0.25-0.42
        v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        shares = fair_vertex_shares(config, 480, v, f)
        assert np.allclose(shares, np.minimum(1.0, (local_thickness(v, f) / 0.2) ** 2))
        if most == 1.0:  # thicker than fair_thickness everywhere: the whole fairing
            assert np.all(shares == 1.0)
        else:
            assert 0.2 < np.median(shares) < most, np.median(shares)
        assert np.all(fair_vertex_shares(config, 128, v, f) == 1.0)
        assert np.all(fair_vertex_shares(dataclasses.replace(config, fair_thickness=0.0), 480, v, f) == 1.0)
    v, f = np.asarray(rod.vertices), np.asarray(rod.faces)
    keep = fair_curvature_share(config, 360)
    assert 0 < keep < 1
    assert np.allclose(fair_vertex_shares(config, 360, v, f), keep + (1 - keep) * fair_vertex_shares(config, 480, v, f))


def test_above_ten_views_the_thick_parts_pull_less_on_full_width_masks():
    """silhouette_vertex_shares: with V > silhouette_views_thick (10) masks at full width, a part at least
    fair_thickness thick gets 10 / V of the silhouette weight and a thin one more, by the same
    (thickness / fair_thickness)^2 as the fairing; 10 views and fewer keep all of it; coarse masks follow
    silhouette_views_thick_coarse (off here, then on) with silhouette_thick_share_coarse's cap from that many
    views on (off, then on), and between, the two blended by coarse_share."""
    from lookingglass.refine import fair_curvature_share, silhouette_thick_share, silhouette_vertex_shares

    rod = trimesh.creation.capsule(height=1.0, radius=0.05, count=[16, 16])  # diameter 0.1: half of 0.2
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.4)  # diameter 0.8
    config = RefineConfig(fair_thickness=0.2, silhouette_views_thick=10, silhouette_views_thick_coarse=0,
                          silhouette_thick_share_coarse=1.0)
    assert RefineConfig().silhouette_views_thick_coarse == 10  # the default: on coarse masks too (session 66)
    assert RefineConfig().silhouette_thick_share_coarse == 0.5  # at most half there from 10 views on (session 67)
    assert silhouette_thick_share(config, 20, 480) == 0.5 and silhouette_thick_share(config, 40, 1920) == 0.25
    assert [silhouette_thick_share(config, v, 480) for v in (5, 10)] == [1.0, 1.0]
    assert silhouette_thick_share(config, 20, 128) == 1.0 == silhouette_thick_share(config, 20, 240)
    plain = 1 - fair_curvature_share(config, 360)
    assert 0 < plain < 1 and np.isclose(silhouette_thick_share(config, 20, 360), 1 - 0.5 * plain)
    v, f = np.asarray(ball.vertices), np.asarray(ball.faces)
    assert np.allclose(silhouette_vertex_shares(config, 20, 480, v, f), 0.5)
    assert np.all(silhouette_vertex_shares(config, 10, 480, v, f) == 1.0)
    assert np.all(silhouette_vertex_shares(config, 20, 128, v, f) == 1.0)
    v, f = np.asarray(rod.vertices), np.asarray(rod.faces)
    shares = silhouette_vertex_shares(config, 20, 480, v, f)
    assert np.allclose(shares, 1 - 0.5 * np.minimum(1.0, (local_thickness(v, f) / 0.2) ** 2))
    assert 0.75 < np.median(shares) < 0.9, np.median(shares)  # the rod's thickness 0.1-0.13: (0.25-0.42) of the fall
    # without a thickness to spare, every part is thick
    assert np.allclose(silhouette_vertex_shares(dataclasses.replace(config, fair_thickness=0.0), 20, 480, v, f), 0.5)
    # off
    assert silhouette_thick_share(dataclasses.replace(config, silhouette_views_thick=0), 20, 480) == 1.0
    # on coarse masks, silhouette_views_thick_coarse's: blended by coarse_share as the full-width one
    coarse = dataclasses.replace(config, silhouette_views_thick=0, silhouette_views_thick_coarse=10)
    assert [silhouette_thick_share(coarse, 20, w) for w in (128, 240, 480)] == [0.5, 0.5, 1.0]
    assert np.isclose(silhouette_thick_share(coarse, 20, 360), 1 - 0.5 * (1 - plain))
    assert np.isclose(silhouette_thick_share(coarse, 20, 300), 0.625)  # coarse_share 0.75: 0.25 x 1 + 0.75 x 0.5
    assert silhouette_thick_share(coarse, 10, 128) == 1.0
    both = dataclasses.replace(coarse, silhouette_views_thick=10)
    assert all(np.isclose(silhouette_thick_share(both, 20, w), 0.5) for w in (128, 360, 480))
    assert np.allclose(silhouette_vertex_shares(coarse, 20, 128, *map(np.asarray, (ball.vertices, ball.faces))), 0.5)
    # the cap on coarse masks, from silhouette_views_thick_coarse views on: the lower of it and 10 / V
    capped = dataclasses.replace(both, silhouette_thick_share_coarse=0.5)
    assert [silhouette_thick_share(capped, v, 128) for v in (5, 9, 10, 15, 20, 40)] == [1, 1, 0.5, 0.5, 0.5, 0.25]
    assert [silhouette_thick_share(capped, v, 480) for v in (5, 10, 20, 40)] == [1.0, 1.0, 0.5, 0.25]
    assert np.isclose(silhouette_thick_share(capped, 10, 300), 0.625)  # coarse_share 0.75: 0.25 x 1 + 0.75 x 0.5
    assert silhouette_thick_share(dataclasses.replace(capped, silhouette_thick_share_coarse=0.3), 10, 240) == 0.3
    assert silhouette_thick_share(dataclasses.replace(capped, silhouette_views_thick_coarse=0), 10, 128) == 1.0
    v, f = np.asarray(ball.vertices), np.asarray(ball.faces)
    assert np.allclose(silhouette_vertex_shares(capped, 10, 128, v, f), 0.5)
    assert np.all(silhouette_vertex_shares(capped, 10, 480, v, f) == 1.0)
    assert np.all(silhouette_vertex_shares(capped, 5, 128, v, f) == 1.0)


def test_the_thick_parts_share_reaches_the_silhouette_constraints(scene, monkeypatch):
    """The per-vertex shares scale each vertex's summed constraint (M, b) and nothing else, and
    `refine_surface` hands the constraints `silhouette_vertex_shares` of its remeshed start, in the
    silhouette iterations and in the normal term's smoothing solve alike; report.json says the share."""
    import lookingglass.refine as refine
    from lookingglass.hull import silhouette_fields

    gt, cameras, masks, hull = scene
    cams = hull.cameras_normalized(cameras).to(device="cpu", dtype=torch.float32)
    fields = torch.as_tensor(silhouette_fields(masks, 0.0))
    x = hull.normalize_points(lumpy_shrunken(gt).vertices)
    s, g = refine.field_values(fields, cams, x)
    weights = np.ones(len(masks))
    shares = np.random.default_rng(0).uniform(0.1, 1.0, len(x))
    whole = refine._constraints(x, np.asarray(gt.faces), s, g, cams, weights, CONFIG, 2.0, np.ones(len(x)))
    part = refine._constraints(x, np.asarray(gt.faces), s, g, cams, weights, CONFIG, 2.0, shares)
    assert whole.rim.any() and np.array_equal(whole.rim, part.rim) and np.array_equal(whole.outside, part.outside)
    assert np.allclose(part.M, whole.M * shares[:, None, None]) and np.allclose(part.b, whole.b * shares[:, None])

    seen = []
    original = refine._constraints
    monkeypatch.setattr(refine, "_constraints", lambda *a: seen.append(a[8]) or original(*a))  # vertex_shares
    # 5 "thick" views below 10: a share of 1 - (1 - 5 / 10) x (1 - coarse_share) at 320 px, on every
    # part (no thickness to spare; the coarse masks' cap off)
    config = dataclasses.replace(CONFIG, iterations=2, silhouette_views_thick=5, fair_thickness=0.0,
                                 silhouette_thick_share_coarse=1.0)
    result = refine_surface(lumpy_shrunken(gt), hull, masks, cameras, config)
    share = refine.silhouette_thick_share(config, len(masks), masks.shape[2])
    assert 0.5 < share < 1 and result.report["silhouette_share_thick"] == pytest.approx(share, abs=1e-4)
    assert len(seen) == 2 and all(np.allclose(v, share) for v in seen)
