"""Typed configuration of `reconstruct`: one dataclass per stage, assembled into PipelineConfig.

The stages' configs live here, not in their stages' modules, so that reading or checking a config
(the command line builds its options from these dataclasses) imports no torch, trimesh or
network: `lookingglass reconstruct` refuses a bad flag or a missing scene folder in well under a
second. Each stage module imports its own (`from .config import RefineConfig`).

The named presets (`cpu`, `paper`) live in lookingglass.presets, with the dataset's and the
trainers' configs. The resolved config is saved (JSON) beside every output and checkpoint, and
`config_from_dict` rebuilds it, refusing unknown keys, so a run folder can be reproduced.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .configio import check_ranges, config_from_dict, config_to_dict, setting  # noqa: F401 (re-exported)
from .errors import ConfigError, LookingGlassError
from .physics.constants import IOR_MAX, IOR_MIN, check_ior, check_ior_range

# the re-rendering against the photos (lookingglass/render/compare.py; the refine stage's keep check)
RERENDER_WIDTH = 240  # half of a 480x360 capture: the error is stable to ~1e-3 and a 10-view render takes seconds
# One jittered sample per pixel, the same (seeded) for every mesh compared: 0.36x the time of 2 x 2, and on
# the validation set the refine stage kept the same meshes (docs/history.md, session 44); the error reads
# ~0.015 higher (the photos are smoother than one sample a pixel).
RERENDER_SAMPLES = 1
# the normal stage's views' consensus (normals/consensus.py): a view's vote counts where its first hit lies
# within this many pixel footprints of the point (1: the best of 0.5-1.5 on the validation set, session 91)
VIEW_CONSENSUS_PX = 1.0
STRATEGIES = ("AV", "NE", "RE")  # the feature mappings of the surface stage (lookingglass/points/features.py)


@dataclass
class HullConfig:
    """Settings of `hull.carve_visual_hull`. Plain fields: `dataclasses.asdict` is JSON-serializable.

    resolution: voxels along the longest side of the (padded) carving box; 128 as in the paper.
    field: "distance" carves the views' signed distances to their silhouettes (sub-voxel surface);
        "binary" carves plain inside/outside occupancy, as the paper's release did (kept for
        comparison: its marching-cubes surface keeps the voxel steps, see docs/benchmarks.md).
    padding: added on every side of the tight box found from the data, as a fraction of the box's
        longest side (0.02 = 2.6 voxels at 128: room for marching cubes to close the surface).
    max_resolution, recarve_lost_share: where the pieces dropped besides the largest one cover more
        than `recarve_lost_share` of some view's mask that the largest piece leaves uncovered (a
        part of the object thinner than a voxel came apart), the box is carved again at twice
        `resolution`, up to `max_resolution` (no second carve where it is not above `resolution`).
    coarse_resolution: voxels along the longest side for the final round of the box search (1/8 of
        the fine carve's voxels at 64 vs 128); earlier rounds use half of it.
    box_iterations: most coarse carve -> shrink rounds of the box search.
    subdivision_iterations, subdivision_threshold: MeshLab "LS3 Loop" subdivision, edges longer
        than `subdivision_threshold` (fraction of the bounding-box diagonal; DESIGN.md: 1%) are
        split, `subdivision_iterations` times. 0 iterations = the raw marching-cubes surface.
    smoothing_iterations: Taubin (lambda/mu, volume preserving) smoothing steps applied to the
        marching-cubes mesh before subdivision; 0 = none.
    min_view_coverage, warn_view_coverage: the hull's projection must cover at least this fraction
        of every view's mask (error below min, warning below warn): a consistency check of masks
        and cameras (consistent synthetic captures give >= 0.99).
    chunk_voxels: voxels carved per batch; bounds the memory to ~ 40 bytes x chunk_voxels.
    num_threads: torch intra-op threads while carving: > 0 exactly that many, 0 = half the cores
        (see `threads.torch_threads`), < 0 = torch's current setting.
    device: torch device for the carving ("cpu", "cuda", ...).
    """

    resolution: int = setting(128, "Voxels along the longest side of the hull box.", range=(16, 1024))
    max_resolution: int = setting(256, "Finest second carve where a thin part of the object came apart at resolution "
                                       "(recarve_lost_share; not above resolution: never).", range=(16, 1024))
    recarve_lost_share: float = setting(0.002, "Share of a view's mask that only the pieces dropped besides the largest "
                                               "cover, above which the hull is carved again finer (max_resolution).",
                                        range=(0, 1))
    field: str = setting("distance", "distance (sub-voxel surface) or binary (the paper release's occupancy).")
    padding: float = setting(0.02, "Margin around the tight box, a fraction of its longest side.", range=(0, 1))
    coarse_resolution: int = setting(64, "Voxels along the longest side in the box search's last round.",
                                     range=(8, 1024))
    box_iterations: int = setting(8, "Most coarse carve -> shrink rounds of the box search.", range=(0, None))
    subdivision_iterations: int = setting(5, "LS3 Loop subdivision rounds (0: the raw marching-cubes surface).",
                                          range=(0, None))
    subdivision_threshold: float = setting(0.01, "Edges longer than this fraction of the box diagonal are split.",
                                           range=(0, 1))
    smoothing_iterations: int = setting(0, "Taubin smoothing steps before subdivision.", range=(0, None))
    min_view_coverage: float = setting(0.5, "Least fraction of every mask the hull must cover (else an error).",
                                       range=(0, 1))
    warn_view_coverage: float = setting(0.9, "Below this fraction of a mask covered: a warning.", range=(0, 1))
    chunk_voxels: int = setting(1 << 20, "Voxels carved per batch (memory ~ 40 bytes each).", range=(1, None))
    num_threads: int = setting(0, "Torch threads while carving (0: half the cores; < 0: torch's setting).")
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.field not in ("distance", "binary"):
            raise ConfigError(f'field must be "distance" or "binary", got {self.field!r}')


@dataclass
class LatentOptConfig:
    """iterations_n2: steps on N2 with N1 held by an identity loss of weight `identity_weight`;
    iterations_both: steps on both. The paper uses 500 + more on a GPU (the `paper` preset: 500 +
    500). Off by default: the steps lower the normals' render error but not their angle errors (the
    sweep in docs/history.md, benchmarks/latent_sweep.py: 10.51 -> 10.48 deg N1 median from 0 to
    40 + 40; the test split's Table 1, 10 + 10: 6.74 -> 6.72 deg), nor the final mesh (session 88:
    the 480x360 test split's first 12 scenes, refined CD 4.74 / 4.66 with 10 + 10 / none, CDN-mean
    6.10 both), and 10 + 10 took ~7 s of a 10-view `reconstruct` on the 2-core machine; the shape
    tables were always measured without them."""

    iterations_n2: int = setting(0, "Latent-optimization steps on N2 (N1 held; 0: none).", range=(0, None))
    iterations_both: int = setting(0, "Latent-optimization steps on N1 and N2 (0: none).", range=(0, None))
    lr: float = setting(5e-3, "Adam step size of the latent optimization.", range=(0, None))
    identity_weight: float = setting(100.0, "Weight of the loss holding N1 during the N2 steps.", range=(0, None))

    def __post_init__(self) -> None:
        check_ranges(self)


@dataclass
class NormalStageConfig:
    """weights: a weights.safetensors path, or "" for the shipped weights of the view count
    nearest `views` (0: the capture's view count). latent: the post-processing (iterations 0 = off).
    consensus_px: the views' consensus (normals/consensus.py; not in the refine stage's second pass).
    mirror_average: the network's answer averaged with its answer for the capture's mirror image
    (normals/predict.py)."""

    weights: str = setting("", "Normal-network weights (\"\": the shipped ones).")
    views: int = setting(0, "Use the shipped weights trained for this view count (5, 10, 20; the nearest that "
                            "ships); 0: the capture's view count.")
    latent: LatentOptConfig = field(default_factory=LatentOptConfig)
    consensus_px: float = setting(VIEW_CONSENSUS_PX, "Make the predicted normals agree across the views that see "
                                  "the same point (within this many pixel footprints; 0: each view's own).",
                                  range=(0, None))
    mirror_average: bool = setting(True, "Average the network's normals with its normals for the mirror image of "
                                   "the capture (twice the network's time).")

    def __post_init__(self) -> None:
        if self.views < 0:
            raise ConfigError(f"views must be 0 (the capture's count) or a view count, got {self.views}")


@dataclass
class SurfaceConfig:
    """points: hull samples for Poisson (with PNet, rounded up to whole clouds of its trained
    size); strategy: AV, NE or RE (feature mapping); depth: Poisson octree depth (8: 1/128 of the
    unit sphere's box, about the hull's 128^3 voxel); point_weight, samples_per_node: screened
    Poisson's; smoothing_neighbours: PNet's offsets and normals are averaged over this many
    nearest points (0 or 1: not at all), see `points.stage.smooth_over_neighbours`; seed: point sampling;
    point_weights: PNet weights ("" = the shipped ones, if any); close_radius: tunnels narrower than
    about twice this many Poisson voxels are filled in a surface with handles (0: never; see
    `points.stage.surface_from_normals`).

    Why 40 000 points: where two parts of the hull face each other across a slit narrower than
    the point spacing (a handle close to the body), Poisson fuses them and the slit's walls vanish.
    On the 10-view test split's worst case (a genus-2 shape, test scene 25), Chamfer distance with
    ground-truth normals went 48.0 (20 000 points) -> 20.7 (40 000) against the hull's 15.9 (depth
    9 or 10 changed nothing: the spacing limits); on other scenes the change was within +-0.1.
    A point weight of 10 got scene 25 to 17.9 but, on PNet's points, opened spurious tunnels
    (a torus came out genus 3), so it stays at MeshLab's 4. Lower weights smooth PNet's surface
    (CDN-mean -1.6 deg at weight 1 on a 16-scene validation split, `generate --split test --seed 1`)
    but fuse slits (test scene 33: CD 24 -> 41 at weight 2, 69 at 1). Neighbours 8/16/32/64 gave the
    same CD within 0.3% on that split and CDN-mean 15.3/14.9/14.6/14.4 deg; 64 starts to average
    across slits (scene 33: CD 24.5 at 32, 25.3 at 64). 32 on the 60-scene test split with the
    shipped PNet, against 16: CD 11.07 vs 11.08, CDN-mean 15.77 vs 16.08, Metro 46.8 vs 47.1.

    Why close_radius 2 (balls of 2 voxels: tunnels under ~0.034 wide in the hull's frame): on the
    5-view test split (first 46 scenes, the shipped PNet, every surface closed) radii 2 / 3 / 4 gave
    CD 18.48 / 18.97 / 19.31 against 18.31 unclosed, and excess handles over the ground truth 59 /
    11 / 4 against 112; from 3 on, real handles narrowed by PNet's inward move close too (scene
    25, genus 2: CD 17.6 -> 26.5 at 3, 39.1 at 4)."""

    points: int = setting(40000, "Points on the hull for the surface (more keeps narrower slits and takes longer).",
                          range=(1, None), cli_range=(1000, 1_000_000))
    strategy: str = setting("RE", "Feature mapping: AV, NE or RE.")
    depth: int = setting(8, "Poisson octree depth.", range=(1, 16))
    point_weight: float = setting(4.0, "Screened Poisson's point weight.", range=(0, None))
    samples_per_node: float = setting(1.5, "Screened Poisson's samples per node.", range=(0, None))
    smoothing_neighbours: int = setting(32, "PNet's offsets and normals are averaged over this many nearest points "
                                            "(0 or 1: not at all).", range=(0, None))
    close_radius: int = setting(2, "Fill tunnels narrower than about twice this many Poisson voxels (0: never).",
                                range=(0, None))
    seed: int = setting(0, "Point-sampling seed.")
    point_weights: str = setting("", "PNet weights (\"\": the shipped ones, if any).")

    def __post_init__(self) -> None:
        if self.strategy.upper() not in STRATEGIES:
            raise ConfigError(f"strategy must be one of {STRATEGIES}, got {self.strategy!r}")
        check_ranges(self)


@dataclass
class RefineConfig:
    """Settings of `refine.refine_surface` (the `refine` stage). Lengths are in the hull-normalized frame
    (max |p| = 1), image distances in the capture's pixels. The weights are relative: each term is
    a sum of squared lengths (silhouette residuals, Laplacians, steps) over the vertices."""

    edge_length: float = setting(0.018, "Edge length of the remeshed surface (hull-normalized frame). 0.018 against "
                                        "0.015: val480 CD 4.52 -> 4.38, CDN-mean 8.18 -> 8.10, Metro 9.25 -> 9.74, "
                                        "~25% less time (the nut 45 000 -> 32 000 vertices); level at 128x96 "
                                        "(docs/history.md, session 49).", range=(0.002, 0.2))
    remesh_iterations: int = setting(3, "Isotropic remeshing passes (0: keep the surface's own triangles).",
                                     range=(0, 50))
    iterations: int = setting(24, "Outer iterations (silhouette constraints re-linearized, one linear solve each).",
                              range=(0, 500))
    max_step_px: float = setting(2.0, "Most a constraint moves its vertex in one iteration, in pixels.",
                                 range=(0.01, None))
    outward_reach: bool = setting(True, "A rim vertex inside its mask whose mask reaches on beyond it, along its "
                                        "silhouette's outward direction, more than a pixel farther than the field's "
                                        "nearest boundary, and whose field deepens outward (that boundary lies behind "
                                        "it, across a thin part), is pushed outward to where the mask ends (up to "
                                        "band_px), not pulled to that nearest boundary (`outward_reach`). The "
                                        "5-view 480x360 test scene 55's handle: worst view 0.964 -> 0.987 "
                                        "(docs/history.md, session 75).")
    band_px: float = setting(24.0, "Rim vertices farther than this from their mask's boundary are not pulled to it "
                             "(12 until session 52: a crescent 12-20 px deep stayed uncovered).",
                             range=(0, None))
    silhouette_weight: float = setting(20.0, "Weight of the rim and outside constraints at masks of silhouette_width "
                                            "pixels or wider.", range=(0, None))
    silhouette_width: int = setting(480, "Mask width at and above which the silhouette and fairing weights apply whole; "
                                         "a narrower mask's are scaled by (width / this)^silhouette_width_power and "
                                         "(width / this)^fair_width_power, and its fairing keeps the mesh's curvature "
                                         "(all of it from half this width down: fair_curvature_share) (0: never "
                                         "scaled).", range=(0, None))
    silhouette_width_power: float = setting(3.0, "How fast the silhouette weight falls below silhouette_width (4.27 "
                                                 "until session 57, with plain fairing).", range=(0, 8))
    fair_width_power: float = setting(2.524, "How fast the fairing weight falls below silhouette_width (2.96 until "
                                             "session 57, when the fairing stopped shrinking coarse masks' meshes: "
                                             "fair_curvature_rings; 2 until session 60, when the fairing at 480 px "
                                             "doubled and 2.524 kept 128 px masks' weight at 14).", range=(0, 8))
    silhouette_views: int = setting(5, "View count at and above which the silhouette weight applies whole on "
                                        "full-width masks; with V fewer views it is multiplied by this / V (0: never "
                                        "scaled).", range=(0, None))
    silhouette_views_coarse: int = setting(10, "The same on coarse masks (coarse_share: half silhouette_width wide and "
                                               "narrower; between, blended). 10 against 5: the 5-view test "
                                               "split (128x96) with every view >= 0.98 on 6 -> 9 of scenes 0-9, CD +1%, "
                                               "CDN-mean +2% (docs/history.md, session 63).", range=(0, None))
    silhouette_views_thick: int = setting(10, "View count above which the silhouette weight on parts at least "
                                              "fair_thickness thick falls as this / V on full-width masks (thinner "
                                              "parts keep more, as (thickness / fair_thickness)^2 says: the fairing "
                                              "shrinks them first; coarse masks: silhouette_views_thick_coarse; 0: "
                                              "never on full-width masks). 20 views (val480v20): CD 3.26 -> 3.14, "
                                              "the key's worst view held (docs/history.md, session 63).",
                                          range=(0, None))
    silhouette_views_thick_coarse: int = setting(10, "The same on coarse masks (coarse_share; between, blended; 0: "
                                                     "never), from this many views on at most "
                                                     "silhouette_thick_share_coarse. 20 views at 240x180 (val240v20): "
                                                     "CD 3.81 -> 3.63, CDN-mean 7.28 -> 7.02, every view >= 0.98 on "
                                                     "9 -> 10 of 10 with the penalty rounds (docs/history.md, "
                                                     "session 66).",
                                                 range=(0, None))
    silhouette_thick_share_coarse: float = setting(0.5, "The most of the silhouette weight parts at least "
                                                        "fair_thickness thick get on coarse masks from "
                                                        "silhouette_views_thick_coarse views on (1: no cap; 20 views: "
                                                        "10 / 20 already; 15 views at 240x180: CD 4.46 -> 4.33, "
                                                        "session 68). 10 views, the test split (128x96): CD 8.59 -> "
                                                        "8.46, CDN-mean 11.57 -> 11.27, every view >= 0.98 on 58 -> 57 "
                                                        "of 60 (docs/history.md, session 67).",
                                                   range=(0, 1))
    silhouette_retries: int = setting(2, "Rounds the stage reruns from its input while a view's silhouette IoU (the kept "
                                         "mesh's, a view of full weight) is below silhouette_iou_target, that view's "
                                         "silhouette weight multiplied by silhouette_retry_factor each round; the "
                                         "round whose worst view is best is kept, of those that keep their refined "
                                         "mesh if any do (0: one round). Test split at 128x96, 10 views, 14 of the 15 "
                                         "scenes below 0.98 reach it (docs/history.md, session 64).", range=(0, 10))
    silhouette_round_gain: float = setting(0.001, "A round whose worst view (its kept mesh's) is not above the best "
                                                  "worst view of the rounds before by more than this ends the rounds "
                                                  "(silhouette_rounds_ended: why the last round was the last): "
                                                  "pushing harder did not help (the 5-view test scene 35 kept its "
                                                  "input in three rounds).",
                                           range=(0, 1))
    silhouette_retry_factor: float = setting(3.0, "What each of silhouette_retries' rounds multiplies a short view's "
                                                  "silhouette weight by (3: 3 x, then 9 x).", range=(1, 100))
    silhouette_retry_backoff: bool = setting(True, "After a round that does not raise the worst view (silhouette_round_gain), "
                                                    "rerun once more from the best round's weights with the factor's square "
                                                    "root instead of ending (after the last of silhouette_retries too: "
                                                    "one round over them), and return it only where "
                                                    "every view reaches silhouette_iou_target: a 3 x pull can overshoot "
                                                    "where a milder one lands (val480's key: 0.9795, then 0.9774 at 3 x, "
                                                    "0.9830 at the square root; docs/history.md, session 69).")
    silhouette_round_without_normals: bool = setting(
        True, "When the rounds end with a view short of silhouette_iou_target and the normal term of a round took a "
              "view that round pulled harder below the target (or lower still below it, by more than keep_tolerance), "
              "one more round at that round's pull without the normal term, returned where it lands every view on the "
              "target (report.json: silhouette_rounds; normal_term.pulled_views_lost). val480's key: worst view "
              "0.9786 -> 0.9846 (docs/history.md, session 76).")
    silhouette_rounds_without_reach: bool = setting(
        True, "When the rounds end with a view short of silhouette_iou_target and a round pushed rims out "
              "(outward_reach), the rounds once more without the reach, returned where they land every view on the "
              "target (report.json: silhouette_rounds' outward_reach). On coarse masks seen by many views the push "
              "can trade one view's sub-pixel rim for another's: the 20-view 128x96 test scene 17 0.9794 -> 0.9803, "
              "val240v20's key 0.9779 -> 0.9801 (docs/history.md, session 78).")
    passes: int = setting(2, "Times the whole stage runs, each pass from the mesh the one before kept, while a pass "
                             "keeps its refined mesh (its keep check weighs it against the previous pass's, so a "
                             "pass never makes the mesh worse on the measures the stage optimizes, nor takes the "
                             "worst view below silhouette_iou_target where the pass before met it). Each pass runs "
                             "the normal net again on a better mesh, and its new targets move the mesh on, where "
                             "more steps against the same targets do not (report.json: passes). 1 -> 2 on val480: "
                             "CD 4.21 -> 3.68, CDN-mean 7.63 -> 7.13 (docs/history.md, session 79).",
                      range=(1, 5))
    short_pass_rounds: bool = setting(False, "Whether a later pass reruns the silhouette rounds (silhouette_retries and "
                                              "the rounds after them) where the pass before ended with a view of full "
                                              "weight below silhouette_iou_target. False: one round, pulling each view "
                                              "as hard as the round the pass before returned (its keep check and the "
                                              "pass check still apply). The 20-view 128x96 test split: 3 of 60 "
                                              "scenes changed, CD 6.05 -> 6.04, CDN-mean 8.09 -> 8.07, every view "
                                              ">= 0.98 on 56 of 60 both times (32 gained, 0 lost), the stage 110 -> "
                                              "102 s a scene (docs/history.md, session 85).")
    extra_pass_views: int = setting(20, "View count from which the stage runs one pass more than passes (0: never). "
                                        "Twenty masks hold the silhouettes, and the third pass's new normals move "
                                        "the concave parts on: val480v20 CD 2.82 -> 2.54 (0.47 -> 0.43 x the hull's; "
                                        "the bracket 7.96 -> 5.62), CDN-mean 5.58 -> 5.41. At 10 views a third pass "
                                        "would cost ~10 s against issue 25's 30 s for the stage (docs/history.md, "
                                        "sessions 80-81).", range=(0, None))
    term_passes: int = setting(0, "Passes past passes (and extra_pass_views' one), at most this many, each run while the "
                                  "pass before kept its refined mesh and its normal term (new normal targets move such "
                                  "a mesh on; where the term was dropped, the next pass's net sees about the mesh it "
                                  "saw). 1 at 10 views: val480 CD 3.69 -> 3.45, CDN-mean 7.04 -> 6.87 (the third pass "
                                  "on 6 of 10); the 480x360 test split's first 8 scenes CD 5.09 -> 4.88, CDN-mean 5.32 "
                                  "-> 5.21 (on 5 of 8, one worse), for ~25% more time in the mean: off by default "
                                  "(docs/history.md, session 90).", range=(0, 4))
    silhouette_iou_target: float = setting(0.98, "The silhouette IoU below which a view pulls harder in the next "
                                                 "round (silhouette_retries; issue 25's bar).", range=(0, 1))
    field_blur_px: float = setting(0.0, "Gaussian blur (sigma, pixels) of the masks' signed-distance fields the "
                                        "silhouette terms pull toward, which irons out the masks' pixel staircase (0: "
                                        "none). 0.7 (edge 0.018): val480 CDN-mean 8.10 -> 7.95, worst IoU 0.981 -> "
                                        "0.985, but at 5 views the mug's handle came off its mask (worst IoU 0.994 -> "
                                        "0.973; docs/history.md, session 49).", range=(0, 4))
    smooth_weight: float = setting(1.0, "Weight of the Laplacian of the displacement (at edge 0.015).",
                                   range=(0, None))
    fair_weight: float = setting(400.0, "Weight of the Laplacian of the positions (fairing; shrinks, but see "
                                       "fair_curvature_rings and fair_thickness; at edge 0.015 and masks "
                                       "silhouette_width wide, scaled below as fair_width_power says; 200 until "
                                       "session 60).", range=(0, None))
    fair_thickness: float = setting(0.2, "Local thickness (shape diameter, hull-normalized frame) below which the plain "
                                         "fairing weakens as (thickness / this)^2: a thin part shrinks under it first "
                                         "(0: uniform fairing; the fairing that keeps the curvature, on coarse masks, "
                                         "does not shrink it and is not weakened; 0 until session 60). Also the "
                                         "thickness above which silhouette_views_thick(_coarse) acts (0: on every part).",
                                    range=(0, None))
    fair_curvature_rings: int = setting(8, "Neighbour-averaging steps that make the fairing's target: each iteration "
                                           "the fairing pulls the Laplacian of the positions toward itself averaged "
                                           "this many times over each vertex's neighbours (a random walk of this "
                                           "many edges, ~sqrt of it wide), which irons out lumps without shrinking a "
                                           "smoothly curved part; on coarse masks only (see fair_curvature_share; "
                                           "0: plain fairing, toward 0).",
                                        range=(0, 64))
    anchor_weight: float = setting(0.05, "Weight of the displacement from the start (keeps each pull local).",
                                   range=(0, None))
    damping: float = setting(0.05, "Weight of the step length (proximal term).", range=(1e-6, None))
    cg_iterations: int = setting(60, "Most conjugate-gradient iterations per linear solve (60 and 200 gave the same "
                                     "meshes on val480 with silhouettes 10 / fairing 100; 60 in 0.6 of the time).",
                                 range=(1, None))
    descent_cg_iterations: int = setting(150, "Most conjugate-gradient iterations of the solve that smooths each normal- or "
                                             "photometric-term step (the silhouette solve's system as a preconditioner).",
                                         range=(1, None))
    view_coverage_full: float = setting(0.97, "A view whose mask the hull covers at least this much has full weight.",
                                        range=(0, 1))
    view_coverage_zero: float = setting(0.8, "A view whose mask the hull covers at most this much has weight 0 (linear up to full).",
                                        range=(0, 1))
    rerender_width: int = setting(RERENDER_WIDTH, "Width the input and refined meshes are re-rendered at to compare them with the "
                                       "photos (a keep-check measure; 0: off).", range=(0, 4096))
    rerender_samples: int = setting(RERENDER_SAMPLES, "Samples per pixel and axis of those re-renderings (the same jittered samples for "
                                       "every mesh compared).", range=(1, 8))
    photometric_iterations: int = setting(0, "Descent steps on the two-bounce photometric loss after the silhouette "
                                             "iterations (0: off; measured not to help yet, docs/results.md).",
                                          range=(0, 500))
    photometric_step: float = setting(0.5, "Largest photometric step, in edge lengths (halved while the loss does not fall).",
                                      range=(0.001, 10))
    photometric_envmap_height: int = setting(64, "Environment-map height the photometric loss looks up (a blurred map "
                                                 "widens the basin).", range=(8, 4096))
    normal_iterations: int = setting(32, "Descent steps pulling the mesh's two-bounce normals toward a second pass of the "
                                      "normal network, fed the mesh in place of the hull, where its gain head says both "
                                      "normals beat the mesh's by more than normal_trust_gain (0: off; skipped for a "
                                      "normal net without a gain head). 32 against 16: val480 CD 0.452 -> 0.441 x the "
                                      "hull's, ~+5 s a scene (docs/history.md, session 48).", range=(0, None))
    normal_step: float = setting(0.5, "Largest normal-term step, in edge lengths (halved while the loss does not fall, "
                                 "grown back by normal_step_growth).",
                                 range=(0, None))
    normal_step_growth: float = setting(2.0, "The normal term's step length times this after a step that lowered its "
                                             "loss (at most normal_step; 1: it only shrinks).", range=(1, 4))
    descent_conjugate: bool = setting(False, "Conjugate (Polak-Ribiere+) directions in the normal and photometric "
                                             "descents: their loss falls ~25% lower in the same steps, but on val480 "
                                             "CD 3.71 -> 3.55 with CDN-mean 7.06 -> 7.15 (worse on 6 of 10), and on "
                                             "30 scenes of the 480x360 test split CD -0.14 +- 0.14, CDN-mean +0.06 +- "
                                             "0.05 (worse on 19): off (docs/results.md, session 96).")
    normal_trust_gain: float = setting(1.0, "A pixel pulls where the gain head predicts the network's normals closer to "
                                            "the truth than the mesh's by more than this, in degrees, at both hits.",
                                       range=(None, None))
    normal_robust: float = setting(0.03, "Scale of the normal term's robust misfit: a ray's 2 - n1.t1 - n2.t2 counts as "
                                        "s m / (s + m), so a ray whose hit jumps to another sheet of the mesh moves the "
                                        "loss by at most s (0: plain mean).", range=(0, None))
    hull_carve: bool = setting(True, "Intersect the refined mesh with the visual hull (manifold3d) when its silhouette "
                                     "spills out of a mask by more than carve_outside_share, and keep the carved mesh "
                                     "when it matches the masks better (mean IoU up by more than keep_tolerance) "
                                     "and re-renders the photos no worse than masks_better_rerender_tolerance allows.")
    input_carve: bool = setting(True, "Intersect the stage's input (the surface) with the visual hull before "
                                      "refining, by hull_carve's rule (its silhouette spills out of a mask by more "
                                      "than carve_outside_share; kept where the masks agree better and the photos "
                                      "allow). A web the surface spans across a hole that some mask shows drags the "
                                      "hole's rim along under the silhouette pull, and no vertex move can open it. "
                                      "5-view 480x360 test scenes 51 and 55: refined CD 22.87 -> 18.54 and 21.57 -> "
                                      "18.68 (docs/history.md, session 74).")
    masks_better_rerender_tolerance: float = setting(
        0.05, "Where the masks say a mesh is better, its re-rendering of the photos may be worse by up to this share: "
              "the hull carve (mean IoU up by more than keep_tolerance) and the keep check's refined mesh (its worst "
              "view and mean IoU both up by more than MASKS_CLEARLY_BETTER); elsewhere RERENDER_TOLERANCE (1%). "
              "Test split at 128x96 (docs/history.md, session 65): 10 views, scene 0's carve refused (+18%: CDN-mean "
              "11.7 -> 7.7, worst view 0.985 -> 0.969); 5 views, scene 55's carve kept (+2.5%; without it CD 24.0 -> "
              "27.4, worst view 0.948 -> 0.886) and scene 35's refined mesh kept (+1.4%; worst view 0.939 -> 0.987, "
              "CD 15.31 -> 13.82).", range=(0, None))
    carve_outside_share: float = setting(0.005, "Share of a view's mask pixels the refined silhouette (the input's, for "
                                                "input_carve) must cover outside it before the hull carve is tried.",
                                         range=(0, 1))
    keep_tolerance: float = setting(0.002, "The refined mesh is kept unless a measure is worse than the input's by "
                                           "more than this (the worst view's IoU; the mean IoU, only where the "
                                           "refined mesh re-renders the photos better by more than 1%, else "
                                           "by keep_iou_noise at most; relative for the roughness).",
                                  range=(0, None))
    keep_iou_noise: float = setting(0.0005, "The mean IoU may also fall by up to this where the refined mesh "
                                            "re-renders the photos no worse: a few pixels a view, rims moved by "
                                            "hundredths of a pixel (docs/history.md, session 89).", range=(0, None))

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.view_coverage_zero >= self.view_coverage_full:
            raise ConfigError(f"view_coverage_zero ({self.view_coverage_zero}) must be below view_coverage_full "
                              f"({self.view_coverage_full})")


STAGES = ("visual_hull", "normals", "surface", "refine")
IOR_CHOICES = ("scene", "auto")  # the words `ior` takes besides a number


def parse_ior(text: str, name: str = "ior", choices: tuple[str, ...] = IOR_CHOICES) -> str | float:
    """PipelineConfig.ior read: one of `choices` ("scene": scene.json's IoR; "auto": estimated from
    the photos, lookingglass/ior.py) as it is, else the number it holds, in [IOR_MIN, IOR_MAX].
    Raises ConfigError naming `name` and the text."""
    if text in choices:
        return text
    try:
        value = float(text)
    except (TypeError, ValueError):
        words = ", ".join(choices)
        raise ConfigError(f"{name} must be {words} or an index of refraction from {IOR_MIN} to {IOR_MAX}, "
                          f"got {text!r}") from None
    return check_ior(value, name, ConfigError)


@dataclass
class PipelineConfig:
    """Everything `reconstruct` needs. device: "cpu", "cuda", "cuda:1", ... ("auto" = cuda if
    present; resolved once, and every stage, the hull's carving included, runs there).
    stop_after: the last of STAGES to run. ior: `parse_ior`'s text, the IoR every stage assumes
    ("auto": IOR_GLASS moved into ior_range, then estimated from the kept mesh and the photos).
    ior_range: (LO, HI), LO < HI: the range `--ior auto` searches."""

    hull: HullConfig = field(default_factory=HullConfig)
    normals: NormalStageConfig = field(default_factory=NormalStageConfig)
    surface: SurfaceConfig = field(default_factory=SurfaceConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    stop_after: str = setting("refine", f"Last stage to run: {', '.join(STAGES)}.")
    device: str = setting("auto", "cpu, cuda, cuda:N or auto (cuda when present).")
    seed: int = setting(0, "Not read by any stage yet (the point sampling takes surface.seed).")
    ior: str = setting("scene", f"Index of refraction of the object: scene (scene.json's), a number from {IOR_MIN} "
                       f"to {IOR_MAX}, or auto: estimated from the photos at the end (ior_estimate).")
    ior_range: tuple[float, float] = setting((1.3, 1.7), f"LO HI, LO < HI, from {IOR_MIN} to {IOR_MAX}: the indices of "
                                             "refraction searched when ior is auto.")

    def __post_init__(self) -> None:
        if self.stop_after not in STAGES:
            raise ConfigError(f"stop_after must be one of {', '.join(STAGES)}, got {self.stop_after!r}")
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ConfigError(f"device must be cpu, cuda, cuda:N or auto, got {self.device!r}")
        parse_ior(self.ior)
        check_ior_range(self.ior_range, "ior_range", ConfigError)

    def resolved(self) -> PipelineConfig:
        """This config with its device resolved ("auto" -> what is present) and the hull carving on
        it: what `reconstruct` runs and saves in report.json."""
        import dataclasses

        device = resolve_device(self.device)
        return dataclasses.replace(self, device=device, hull=dataclasses.replace(self.hull, device=device))

    @classmethod
    def from_json(cls, path) -> PipelineConfig:
        """The config of a finished run: its report.json (the "config" entry) or a config JSON."""
        from .fileio import read_json

        data = read_json(path, "config")
        if isinstance(data, dict) and "config" in data:
            data = data["config"]
        try:
            return config_from_dict(cls, data, where=str(path))
        except (TypeError, ValueError) as exc:
            raise LookingGlassError(f"invalid config ({exc})", path) from None


def resolve_device(name: str) -> str:
    """'auto' -> 'cuda' when a GPU is present, else 'cpu'; an unavailable CUDA device is an error.
    torch is imported only to look for a GPU (not for 'cpu' or a misspelt name)."""
    import re

    if name not in ("auto", "cpu", "cuda") and not re.fullmatch(r"cuda:\d+", name):
        raise LookingGlassError(f"device must be cpu, cuda, cuda:N or auto, got {name!r}")
    if name == "cpu":
        return name
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise LookingGlassError(f"device '{name}' requested but CUDA is not available")
    if name.startswith("cuda:") and int(name[5:]) >= torch.cuda.device_count():
        count = torch.cuda.device_count()
        raise LookingGlassError(f"device '{name}' requested but this machine has {count} CUDA device(s): "
                                f"cuda:0 to cuda:{count - 1}")
    return name
