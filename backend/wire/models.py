"""The HTTP API's data: Pydantic models (extra fields forbidden) and the OpenAPI pieces
that FastAPI cannot infer, such as raw binary bodies.

The AO settings of a request are fields of `AoOptions` (scenesort/ao_options.py, which
imports no engine): `ao_setting` gives each its type, default, range, choices and
documentation from there, and `AoSettings.options()` checks them together there.
(No `from __future__ import annotations`: the fields' types are calls, evaluated here.)
"""

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from scenesort.backend.wire.problems import ApiError

from scenesort.ao_options import AO_OPTIONS, AoOptions, OptionError

OCTET = "application/octet-stream"
Method = Literal["sah", "median"]  # the BVH builders
# a job's images beside AO, coverage, depth
ExtraPass = Literal["normal", "position", "object", "triangle"]
EXTRA_PASSES = ("normal", "position", "object", "triangle")
LeafSize = Annotated[int, Field(ge=1, le=64)]


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ErrorBody(Strict):
    """An RFC 9457 problem document (media type application/problem+json)."""

    type: str = Field(description="tag:scenesort,2026:<code>, e.g. ...:bad_body_length")
    title: str = Field(description="the HTTP status's phrase")
    status: int
    detail: str = Field(description="what is wrong, in words")
    parameter: str = Field(description="the query/path/body parameter or header at fault")
    fix: str = Field(description="what the client should change")


class CacheUse(Strict):
    bytes: int
    max_bytes: int
    scenes: int
    bvhs: int
    evictions: int


class Health(Strict):
    """Without the token only status and versions; with it also the rest."""

    status: Literal["ok"] = "ok"
    version: str
    warp_version: str
    device: str | None = None
    devices: list[str] | None = None  # every Warp device here ("cpu", "cuda:0", ...)
    cache: CacheUse | None = None
    queued: int | None = None
    active_jobs: int | None = None
    max_body_bytes: int | None = Field(
        default=None, description="the largest binary body (an upload) this service takes: "
                                  "clients check theirs before they hash or send it")


class SceneInfo(Strict):
    scene_id: str
    vertices: int
    triangles: int
    bounds: list[list[float]] = Field(description="[[xmin, ymin, zmin], [xmax, ymax, zmax]]")
    degenerate: int = Field(description="zero-area triangles (kept, never hit)")
    normals: bool = Field(description="whether the scene has shading normals (else flat)")
    bytes: int


class InstanceSceneInfo(Strict):
    """An instance list on the service: its meshes (by id) under per-instance transforms."""

    scene_id: str
    meshes: list[str] = Field(description="the mesh ids the instances refer to, in order")
    instances: int
    triangles: int = Field(description="triangles the instances stand for (not stored again)")
    bounds: list[list[float]] = Field(description="[[xmin, ymin, zmin], [xmax, ymax, zmax]]")
    bytes: int = Field(description="bytes of the instance list (the meshes are apart)")
    visibility: dict[str, int] = Field(
        description="instances by ray visibility: camera (seen), shadow (occluding), holdout "
                    "(seen as holdout); every instance counts in camera and shadow when the "
                    "list was sent without masks")


class BuildReport(Strict):
    """What a job did to have its BVHs (render/bvhs.py's skip rules)."""

    built: list[str] = Field(description="mesh ids whose BVH was built from scratch")
    refit: list[str] = Field(description="mesh ids refit from an earlier mesh of the same "
                             "topology (a deformed mesh)")
    reused: list[str] = Field(description="mesh ids whose cached BVH was used as it was")
    top_level: Literal["built", "reused", "none"] = Field(
        description="the instance list's top level (none: a single-mesh scene)")
    culled: int = Field(description="instances out of the camera's view widened by the AO "
                        "distance: left out of the top level (they change no pixel)")
    skipped: list[str] = Field(description="mesh ids with no instance in view: no BVH made "
                               "or used for this render")
    bvh_bytes: int = Field(description="device bytes of what the render traces (the BVHs "
                           "of the meshes it needs and the top level)")
    timings_ms: dict[str, float] = Field(description="cull, build, refit, top_level: ms spent")


class BvhRequest(Strict):
    method: Method = "sah"
    leaf_size: LeafSize = 8


class BvhStats(Strict):
    nodes: int
    leaves: int
    depth: int
    sah_cost: float
    triangles: int
    degenerate: int


class BvhInfo(Strict):
    scene_id: str
    method: Method
    leaf_size: int
    cached: bool = Field(description="true when an earlier build was reused")
    timings_ms: dict[str, float] = Field(
        description="total and one entry per build phase; compile: Warp's, not in total")
    stats: BvhStats


class CameraModel(Strict):
    """Blender's camera model: the wire form of kernels.Camera (kernels/render/camera.py)."""

    matrix_world: Annotated[
        list[Annotated[list[float], Field(min_length=4, max_length=4)]],
        Field(min_length=4, max_length=4, description="4x4 camera-to-world, row-major"),
    ]
    width: Annotated[int, Field(ge=1, le=65536)]
    height: Annotated[int, Field(ge=1, le=65536)]
    type: Literal["PERSP", "ORTHO"] = "PERSP"
    lens: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 50.0
    sensor_width: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 36.0
    sensor_height: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 24.0
    sensor_fit: Literal["AUTO", "HORIZONTAL", "VERTICAL"] = "AUTO"
    ortho_scale: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 6.0
    shift_x: Annotated[float, Field(allow_inf_nan=False)] = 0.0
    shift_y: Annotated[float, Field(allow_inf_nan=False)] = 0.0
    clip_start: Annotated[float, Field(ge=0, allow_inf_nan=False)] = 0.1
    clip_end: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1000.0
    aperture_size: Annotated[float, Field(
        ge=0, allow_inf_nan=False,
        description="depth of field (rendered through a pixel filter): the lens's radius in "
                    "world units, Cycles' lens * 1e-3 / (2 * f-stop) for PERSP, 1 / (2 * "
                    "f-stop) for ORTHO; 0: none")] = 0.0
    focus_distance: Annotated[float, Field(
        gt=0, allow_inf_nan=False, description="the camera-space depth in focus")] = 10.0
    aperture_blades: Annotated[int, Field(
        ge=0, le=16, description="0: a round aperture, else a polygon of 3..16 corners")] = 0
    aperture_rotation: Annotated[float, Field(
        allow_inf_nan=False, description="the polygon's rotation, radians")] = 0.0
    aperture_ratio: Annotated[float, Field(
        gt=0, allow_inf_nan=False, description="anamorphic squeeze of the aperture across x",
    )] = 1.0


class Window(Strict):
    """A rectangle of the frame in pixels, from its left and top edges (a border render)."""

    x: Annotated[int, Field(ge=0, le=65535)]
    y: Annotated[int, Field(ge=0, le=65535)]
    width: Annotated[int, Field(ge=1, le=65536)]
    height: Annotated[int, Field(ge=1, le=65536)]


PixelAspect = Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)]


RMSE_ESTIMATE_DOC = (
    "the render's estimate of its RMSE over hit pixels against the converged AO (AO in "
    "[0, 1]), from the per-pixel sample variances; of the raw render, also when denoised"
)


def ao_setting(name: str) -> Any:
    """The type of the AO setting `name` in a request, as AoOptions defines it (AO_OPTIONS):
    its kind (a Literal of its choices; null too where it is optional), its default, its
    range (at most `soft_high` where it has one: what a request may ask), finite numbers
    only, and its documentation (OpenAPI's description)."""
    spec = AO_OPTIONS[name]
    kind: Any = Literal[spec.choices] if spec.choices else spec.kind
    bounds: dict[str, Any] = {}
    if spec.low is not None:
        bounds["gt" if spec.low_open else "ge"] = spec.low
    if spec.soft_high is not None:
        bounds["le"] = spec.soft_high
    elif spec.high is not None:
        bounds["lt" if spec.high_open else "le"] = spec.high
    if spec.kind is float:
        bounds["allow_inf_nan"] = False
    return Annotated[kind | None if spec.optional else kind,
                     Field(default=spec.default, description=spec.doc, **bounds)]


class AoSettings(Strict):
    """The AO settings a request may set (the others keep AoOptions' defaults: max_spp,
    sampler; terminator offsets travel with the scene, threads are the service's)."""

    spp: ao_setting("spp")
    distance: ao_setting("distance")
    seed: ao_setting("seed")
    target_error: ao_setting("target_error")
    max_pixel_error: ao_setting("max_pixel_error")
    engine: ao_setting("engine")

    def options(self, **service: Any) -> AoOptions:
        """The settings as AoOptions, with the service's own (`threads`), checked there
        together (spp against max_spp with an error target): what it refuses is an
        ApiError 422 naming the setting and the fix."""
        mine = {k: getattr(self, k) for k in type(self).model_fields if k in AO_OPTIONS}
        try:
            return AoOptions(**mine, **service)
        except OptionError as exc:
            raise ApiError(422, exc.name, str(exc), exc.fix, "invalid_parameter") from None


class AoQuery(AoSettings):
    """The query of POST /v1/scenes/{scene_id}/ao: the rays' count, the AO settings and
    which BVH (method and leaf_size unset: the scene's latest). Names it does not know are
    ignored, as a query string's are."""

    model_config = ConfigDict(extra="ignore")

    rays: Annotated[int, Field(ge=1, le=2**27)]
    method: Method | None = None
    leaf_size: LeafSize | None = None


class SurfaceJobQuery(AoSettings):
    """The query of POST /v1/scenes/{scene_id}/surface-jobs: the points' count, the AO
    settings and the BVH to trace (built or reused)."""

    model_config = ConfigDict(extra="ignore")

    points: Annotated[int, Field(ge=1, le=2**27)]
    method: Method = "sah"
    leaf_size: LeafSize = 8


class JobRequest(AoSettings):
    scene_id: Annotated[str, Field(pattern=r"^[0-9a-f]{32}$")]
    camera: CameraModel
    window: Window | None = Field(
        default=None, description="render only this part of the camera's frame (null: all)"
    )
    pixel_aspect: tuple[PixelAspect, PixelAspect] = Field(
        default=(1.0, 1.0), description="Blender's pixel aspect (x, y): a pixel's shape"
    )
    method: Method = "sah"
    leaf_size: LeafSize = 8
    denoise: ao_setting("denoise")
    depth: bool = Field(
        default=True, description="false: no Z pass (the camera rays' closest hits are not "
                                  "traced a second time for it), as a viewport's rounds ask")
    passes: list[ExtraPass] = Field(
        default_factory=list, max_length=len(EXTRA_PASSES),
        description="extra images to keep for GET .../result: normal (world-space shading "
                    "normal, xyz), position (world-space hit point, xyz), object (the "
                    "instance index the camera ray hit, -1 on background and holdouts), "
                    "triangle (the triangle it hit in its instance's mesh, as two values "
                    "exact in float32: index // 65536 and index % 65536; -1 and -1 on "
                    "background and holdouts)")
    pixel_filter: ao_setting("pixel_filter")
    filter_width: ao_setting("filter_width")


FILM_DOC = (
    "what the image's pixels are: 'BLACKMAN_HARRIS 1.5 px' (the pixel filter and width it "
    "was rendered through), 'pixel centres' (filter_width 0), or 'pixel centres: ...' "
    "saying why a requested filter was not used (it needs engine bvh and no denoising)"
)


class JobStatus(Strict):
    job_id: str
    scene_id: str
    state: Literal["queued", "running", "done", "failed", "cancelled"]
    phase: str
    progress: float = Field(ge=0, le=1)
    width: int
    height: int
    timings_ms: dict[str, float]
    spp_mean: float | None = Field(description="mean samples per hit pixel")
    spp_max: int | None = Field(description="most samples any pixel took")
    rmse_estimate: float | None = Field(description=RMSE_ESTIMATE_DOC)
    rays: int | None = Field(description="rays traced: primary and occlusion")
    build: BuildReport | None = Field(
        default=None, description="what the job built, refit or reused (once it has its BVH)")
    denoised: bool | None = Field(default=None,
                                  description="the image is OIDN's output (denoise=true)")
    film: str | None = Field(default=None, description=FILM_DOC)
    error: str | None


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries: each listed status returns an ErrorBody."""
    problem = {"application/problem+json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}
    return {code: {"model": ErrorBody, "content": problem} for code in codes}


def binary_body(description: str) -> dict[str, Any]:
    """OpenAPI for a raw little-endian body (FastAPI cannot infer it from the signature)."""
    return {
        "requestBody": {
            "required": True,
            "description": description,
            "content": {OCTET: {"schema": {"type": "string", "format": "binary"}}},
        }
    }
