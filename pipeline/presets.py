"""Model presets: the one source of truth for geometry, network sizes and thresholds.

A preset feeds training (models/), the ONNX manifest (export/) and the runtime
(pipeline/, service/); a test checks they agree. ``paper`` is the paper's
configuration; ``edge`` is designed to train and run on a 2-core CPU; ``tiny``
keeps tests fast.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class BevGrid:
    """Bird's-eye-view grid in the LiDAR frame.

    Layout of the voxelized tensor: float32 (channels, ny, nx); axis 1 = y bins
    from ``y_min`` upward, axis 2 = x bins from ``x_min``; channel k < nz is the
    occupancy of height slice [z_min + k·z_cell, z_min + (k+1)·z_cell); channel nz
    is the mean reflectance of the cell's points.

    split_pseudo: pseudo points get their own nz occupancy channels after the
    reflectance (channels nz + 1 … 2·nz), so the first nz + 1 channels are exactly
    a LiDAR-only PIXOR's input and the network can tell a return from a guess.
    Without it (the paper's way) pseudo and real points share the occupancy.
    """

    x_min: float = 0.0
    x_max: float = 70.0
    y_min: float = -40.0
    y_max: float = 40.0
    z_min: float = -2.5
    z_max: float = 1.0
    cell: float = 0.1
    z_cell: float = 0.1
    split_pseudo: bool = False

    @property
    def nx(self) -> int:
        return round((self.x_max - self.x_min) / self.cell)

    @property
    def ny(self) -> int:
        return round((self.y_max - self.y_min) / self.cell)

    @property
    def nz(self) -> int:
        return round((self.z_max - self.z_min) / self.z_cell)

    @property
    def channels(self) -> int:
        return 2 * self.nz + 1 if self.split_pseudo else self.nz + 1

    @property
    def lidar_channels(self) -> int:
        """Channels a LiDAR-only PIXOR reads: the real points' occupancy and the reflectance."""
        return self.nz + 1

    @property
    def shape(self) -> tuple[int, int, int]:
        """(channels, ny, nx) of the voxelized tensor."""
        return (self.channels, self.ny, self.nx)


# The depth net's full-resolution head: its correction added to the upsampled depth, or convex upsampling weights.
REFINE_MODES = ("add", "convex")
# PIXOR's four bottleneck stages (block2 … block5) and the cumulative stride of each: the FPN reads from the
# output level up to /16, so the output stride is one of the first three (models/pixor.py).
PIXOR_STAGE_STRIDES = (2, 4, 8, 16)


@dataclass(frozen=True)
class DepthNetConfig:
    """Depth-completion network (Ma et al. sparse-to-dense, ResNet-18 encoder, GAMs, ASPP).

    input_hw: (height, width) the network sees, after the KITTI crop and an
    optional resize by ``input_scale``; stem_stride 1 is the paper (layer1 at
    full resolution), 2 halves every feature map.
    """

    input_hw: tuple[int, int] = (352, 1216)
    input_scale: float = 1.0  # crop is resized by this before the network
    stem_stride: int = 1
    depth_stem: int = 16  # conv1_d output channels
    image_stem: int = 48  # conv1_img output channels
    encoder_widths: tuple[int, int, int, int] = (64, 128, 256, 512)
    encoder_blocks: tuple[int, int, int, int] = (2, 2, 2, 2)  # ResNet-18
    bottleneck_width: int = 512  # conv6
    decoder_widths: tuple[int, int, int, int, int] = (256, 128, 64, 64, 64)  # convt5 … convt1
    use_gam: bool = True
    use_aspp: bool = True
    aspp_rates: tuple[int, ...] = (2, 4, 8, 16)
    # Prefill (0 = off, the paper): the sparse input is filled inside the network by this many
    # max-pool passes over inverse depth (the nearest return wins), fed to conv1_d beside the
    # sparse map, and the network predicts a correction to it (models/depth_net.py says why).
    prefill_passes: int = 0
    prefill_kernel: tuple[int, int] = (5, 3)  # rows × columns per pass: beams are rows apart
    # A second correction at the input resolution (stem stride 2 with the prefill; 0 = off): this many
    # channels in its head (models/depth_net.py, FullResolutionRefine, says why).
    refine_channels: int = 0
    # How that head corrects: "add" a second correction, or "convex": upsample the half-resolution
    # correction as a learned convex combination of its 3×3 neighbours (ConvexUpsample says why).
    refine_mode: str = "add"
    min_depth: float = 0.9  # metres, output floor at inference (Ma et al.)
    max_depth: float = 85.0  # metres: the pseudo cloud keeps depths up to this (the weights do not depend on it)


@dataclass(frozen=True)
class PixorConfig:
    """PIXOR detector: stem, bottleneck stages, FPN top-down path, header."""

    stem_channels: int = 32
    stage_widths: tuple[int, int, int, int] = (24, 48, 64, 96)  # bottleneck widths, ×4 expansion
    stage_blocks: tuple[int, int, int, int] = (3, 6, 6, 3)
    expansion: int = 4
    # One width for every FPN level, or one per level from the output level up to /16: PIXOR's own
    # top-down path is 196 → 128 → 96, (96, 128, 196) here.
    fpn_channels: int | tuple[int, ...] = 96
    header_channels: int = 96
    header_convs: int = 4
    output_stride: int = 4
    prior: float = 0.01  # score bias initialisation


@dataclass(frozen=True)
class DecodeConfig:
    """Turning network outputs into boxes, shared by export, runtime and evaluation."""

    # Regression targets (cos θ, sin θ, dx, dy, log w, log l) are normalised as (t - mean) / std.
    reg_mean: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.49, 1.36)
    reg_std: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 0.1, 0.1)
    score_threshold: float = 0.5
    nms_iou: float = 0.1
    max_candidates: int = 500  # top-scoring cells kept before NMS
    max_detections: int = 100
    car_height: float = 1.53  # metres, when too few points lie inside a box
    ground_z: float = -1.73  # metres, road level in the LiDAR frame (KITTI's sensor height)
    min_occupied_for_height: int = 4  # occupied BEV voxels inside a box needed to measure its height
    # A measured height is averaged with car_height, weighted by the occupied volume under the box
    # against this volume (m³): a sparsely seen car keeps about the mean height (docs/models.md, "Box heights").
    height_prior_volume: float = 0.48
    # Pseudo points whose depth jumps by more than this fraction to a 4-neighbour pixel (the smear
    # between a car and what is behind it) do not count for heights; PIXOR still sees them.
    height_max_jump: float = 0.1
    # Where in the lowest occupied height slice a box's bottom sits (0 its lower edge, 0.5 its centre).
    # Real returns start on the car's body, above the road; the camera pipeline's pseudo points take in
    # the road beside the car with some noise, which put its boxes about 0.1 m low (tuning frames).
    bottom_in_slice: float = 0.0
    bottom_in_slice_with_pseudo: float = 0.5
    pseudo_stride: int = 1  # keep every k-th pseudo point (rows and columns)
    pseudo_max_height: float = 1.0  # metres above the LiDAR, drop pseudo points above (sky, trees)


@dataclass(frozen=True)
class Preset:
    """Everything a model directory needs to be run the same way everywhere."""

    name: str
    depth: DepthNetConfig = field(default_factory=DepthNetConfig)
    pixor: PixorConfig = field(default_factory=PixorConfig)
    bev: BevGrid = field(default_factory=BevGrid)
    decode: DecodeConfig = field(default_factory=DecodeConfig)
    crop_hw: tuple[int, int] = (352, 1216)  # the KITTI depth-completion crop

    @property
    def pseudo_limits(self) -> tuple[float, float, int, float]:
        """Which pseudo points exist: (min_depth, max_depth, stride, max_height), the arguments of
        :func:`pipeline.pseudo.depth_to_points` and :func:`pipeline.bev.pseudo_bins` after the grid."""
        return (self.depth.min_depth, self.depth.max_depth, self.decode.pseudo_stride, self.decode.pseudo_max_height)

    def to_dict(self) -> dict:
        """Plain JSON-able form, as written into the ONNX manifest."""
        return asdict(self)

    def described(self) -> dict[str, dict]:
        """What the manifest's descriptive tables say of this preset, for runtimes other than this one: the
        grid (``bev_grid``) and the constants of the stages around the networks (part of ``normalisation``).
        This runtime runs ``preset_config``; :func:`pipeline.model_files.check_descriptions` holds the two to
        agree."""
        grid = self.bev
        return {
            "bev_grid": {**asdict(grid), "shape": list(grid.shape), "nx": grid.nx, "ny": grid.ny, "nz": grid.nz},
            "normalisation": {
                "min_depth": self.depth.min_depth, "max_depth": self.depth.max_depth,
                "input_scale": self.depth.input_scale, "crop_hw": list(self.crop_hw),
                "regression_mean": list(self.decode.reg_mean), "regression_std": list(self.decode.reg_std),
            },
        }


PRESETS: dict[str, Preset] = {
    # The paper: full-resolution depth net, PIXOR with its own FPN widths on the 0.1 m, 36-channel grid
    # (tests/test_paper_fidelity.py pins each number to DESIGN.md).
    "paper": Preset(name="paper", pixor=PixorConfig(fpn_channels=(96, 128, 196))),
    # Designed for a 2-core CPU: half-resolution depth input with a strided stem and
    # narrower widths; PIXOR on a 0.2 m grid with 0.2 m height slices and halved widths.
    "edge": Preset(
        name="edge",
        depth=DepthNetConfig(
            input_hw=(176, 608), input_scale=0.5, stem_stride=2, depth_stem=8, image_stem=16,
            encoder_widths=(24, 48, 96, 192), bottleneck_width=192, decoder_widths=(96, 48, 24, 24, 24),
            prefill_passes=4,  # 16 beams are 7–15 rows apart at half resolution: ±8 rows closes the gaps
        ),
        pixor=PixorConfig(
            stem_channels=16, stage_widths=(12, 24, 32, 48), stage_blocks=(2, 3, 3, 2),
            fpn_channels=48, header_channels=48, header_convs=2,
        ),
        # x_max 70.4: 352 columns, a multiple of the output stride 4 (70 m would give 350).
        bev=BevGrid(cell=0.2, z_cell=0.2, z_max=1.1, x_max=70.4),
    ),
    # For tests only: small and fast, same code paths.
    "tiny": Preset(
        name="tiny",
        depth=DepthNetConfig(
            input_hw=(88, 304), input_scale=0.25, stem_stride=2, depth_stem=4, image_stem=12,
            encoder_widths=(16, 16, 32, 32), encoder_blocks=(1, 1, 1, 1), bottleneck_width=32,
            decoder_widths=(32, 16, 16, 16, 16), aspp_rates=(2, 4), prefill_passes=2,
        ),
        pixor=PixorConfig(
            stem_channels=8, stage_widths=(4, 8, 8, 8), stage_blocks=(1, 1, 1, 1),
            fpn_channels=16, header_channels=16, header_convs=1,
        ),
        bev=BevGrid(cell=0.4, z_cell=0.5, x_max=70.4),  # 176 columns: divisible by the output stride 4
    ),
}


# Suffixes that change a part of a preset: the paper's two ablations of the depth net, the depth net's
# full-resolution head in its two modes (experiments, docs/models.md: neither lifted the camera row), and
# the BEV with the pseudo points in channels of their own (BevGrid.split_pseudo).
ABLATIONS: dict[str, tuple[str, dict[str, Any]]] = {
    "-no-gam": ("depth", {"use_gam": False}),
    "-no-aspp": ("depth", {"use_aspp": False}),
    "-refine": ("depth", {"refine_channels": 8}),
    "-convex": ("depth", {"refine_channels": 8, "refine_mode": "convex"}),
    "-split": ("bev", {"split_pseudo": True}),
    # Pseudo points only up to 35 m: beyond, the edge depth net puts most of a car's pixels off the car and
    # the camera PIXOR found fewer far cars than the 16-line one (docs/models.md, session 25).
    "-near35": ("depth", {"max_depth": 35.0}),
}


# Where presets come from, for the messages that send a user there (docs/models.md, "Adding a preset").
PRESET_SOURCES = ("registered in pipeline/presets.py, or a preset file: a path ending in .json "
                  "(docs/models.md, \"Adding a preset\")")


def get_preset(name: str) -> Preset:
    """Look up a preset by name, or read it from a JSON file (a ``name`` ending in ``.json``), and check it
    (:func:`check_preset`); errors list the valid names and say where presets come from.

    A suffix ``-no-gam`` or ``-no-aspp`` (e.g. ``edge-no-gam``) gives the paper's
    ablation: the same preset with that part of the depth net switched off;
    ``-refine`` (edge and tiny) adds the depth net's full-resolution correction head, ``-convex``
    the same head upsampling the half-resolution correction instead (``refine_mode``);
    ``-split`` gives the pseudo points their own BEV channels (:class:`BevGrid`), ``-near35`` keeps
    the pseudo points up to 35 m only (``DepthNetConfig.max_depth``; the depth net's weights do not depend on it).
    Suffixes stack (``edge-refine-no-gam``, ``edge-split-near35``). A file is read by :func:`preset_from_file`.
    """
    if not is_preset_file(name):
        preset = registered_preset(name)
        check_preset(preset)
        return preset
    preset = preset_from_file(name)
    try:
        check_preset(preset)
    except ValueError as exc:
        raise ValueError(f"preset file {name}: {exc}") from None
    return preset


def is_preset_file(name: str) -> bool:
    """Whether ``--preset`` names a preset file rather than a registered preset (no name ends in .json)."""
    return name.lower().endswith(".json")


def registered_preset(name: str) -> Preset:
    """A preset of :data:`PRESETS` by name, with ablation suffixes (:func:`get_preset`), unchecked."""
    base = name
    changes: dict[str, dict[str, Any]] = {"depth": {}, "bev": {}}
    applied: set[str] = set()
    while base not in PRESETS:
        suffix = next((s for s in ABLATIONS if base.endswith(s)), None)
        if suffix is None:
            choices = ", ".join(list(PRESETS) + [f"{p}{s}" for p in PRESETS for s in ABLATIONS][:2] + ["…"])
            raise ValueError(f"unknown preset {name!r}; choose one of {choices} ({PRESET_SOURCES})")
        if suffix in applied:  # edge-no-gam-no-gam: a name built twice over, which would pass for another preset
            raise ValueError(f"preset {name!r}: {suffix[1:]} given twice")
        applied.add(suffix)
        part, change = ABLATIONS[suffix]
        changes[part] = {**change, **changes[part]}
        base = base[: -len(suffix)]
    preset = PRESETS[base]
    if base == name:
        return preset
    return replace(preset, name=name, depth=replace(preset.depth, **changes["depth"]),
                   bev=replace(preset.bev, **changes["bev"]))


# The largest number a preset file may give (sizes in metres or cells, channel counts): far above any real one,
# far below what overflows the grid's arithmetic (x_max 1e308 raised an OverflowError).
MAX_PRESET_NUMBER = 1e6
# A preset file's sections and the dataclass each one builds.
SECTIONS: dict[str, type] = {"depth": DepthNetConfig, "pixor": PixorConfig, "bev": BevGrid, "decode": DecodeConfig}


def preset_from_file(path: str | Path) -> Preset:
    """Read a preset file (docs/models.md, "Adding a preset"), unchecked.

    Either a whole preset, as ``Preset.to_dict()`` writes it (a manifest's ``preset_config``): ``name``,
    ``crop_hw`` and the four sections, a field left out of a section taking the dataclass's default as in
    :func:`preset_from_dict`; or ``{"base": "edge", "name": "highway", "bev": {"x_max": 100.0}}``: the
    registered preset ``base`` (suffixes allowed) with the fields given replacing its own. A misspelt key or
    a value of the wrong type is refused naming it, not passed on to fail later.
    """
    where = f"preset file {path}"
    config = _read_object(where, Path(path).expanduser())
    allowed = ["base", "name", "crop_hw", *SECTIONS]
    unknown = [key for key in config if key not in allowed]
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r}{_did_you_mean(unknown[0], allowed)} "
                         f"(keys: {', '.join(allowed)})")
    name = config.get("name")
    if not isinstance(name, str) or not name or is_preset_file(name):
        raise ValueError(f"{where}: 'name' must be the preset's name, a string (checkpoints and manifests record it)")
    start = _file_base(where, config, name)
    parts: dict[str, Any] = {}
    for section, cls in SECTIONS.items():
        given = config.get(section, {})
        held = None if isinstance(given, dict) else type(given).__name__
        if held:
            raise ValueError(f"{where}: {section} must be an object of fields, not {held}")
        parts[section] = replace(getattr(start, section), **_section_fields(where, section, cls, given))
    crop_hw = _field_value(where, "crop_hw", config["crop_hw"], "tuple[int, int]") if "crop_hw" in config else start.crop_hw
    preset = Preset(name=name, crop_hw=crop_hw, **parts)
    _check_not_registered(where, preset)
    return preset


def _refuse_constant(name: str) -> None:
    """json's NaN, Infinity and -Infinity: no size or threshold of a preset is one."""
    raise ValueError(f"{name} is not a number a preset holds")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object's members, refusing a key given twice: json keeps the last silently, and which of two
    grids a preset meant is not for the reader to guess."""
    seen: set[str] = set()
    for key, _ in pairs:
        if key in seen:
            raise ValueError(f"key {key!r} is given twice in one object")
        seen.add(key)
    return dict(pairs)


def _read_object(where: str, path: Path) -> dict:
    """The JSON object in ``path``; ValueError naming the file (and the line of a syntax error) otherwise."""
    try:
        config = json.loads(path.read_text(encoding="utf-8"), parse_constant=_refuse_constant,
                            object_pairs_hook=_unique_keys)
    except OSError as exc:
        raise ValueError(f"{where}: cannot be read ({exc.strerror or type(exc).__name__})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{where}: not UTF-8 text") from None
    except RecursionError:  # Python's parser recurses once per bracket
        raise ValueError(f"{where}: lists and objects nested too deep to be a preset") from None
    except ValueError as exc:  # _refuse_constant's and _unique_keys'
        raise ValueError(f"{where}: {exc}") from None
    held = None if isinstance(config, dict) else type(config).__name__
    if held:
        raise ValueError(f"{where}: holds a JSON {held}, not an object with the preset's sections")
    return config


def _file_base(where: str, config: dict, name: str) -> Preset:
    """What a preset file's sections change: its ``base`` preset, or the dataclasses' defaults for a whole preset
    (which must then give every section)."""
    if "base" not in config:
        missing = [key for key in ("crop_hw", *SECTIONS) if key not in config]
        if missing:
            raise ValueError(f"{where}: lacks {', '.join(missing)}; give the whole preset (Preset.to_dict(), a "
                             "manifest's preset_config) or a \"base\" preset whose sections it changes")
        return Preset(name=name)
    if not isinstance(config["base"], str) or is_preset_file(config["base"]):
        raise ValueError(f"{where}: 'base' must name a registered preset, e.g. \"edge\"")
    try:
        return registered_preset(config["base"])
    except ValueError as exc:
        raise ValueError(f"{where}: base: {exc}") from None


def _section_fields(where: str, section: str, cls: type, given: dict) -> dict[str, Any]:
    """The fields of one section of a preset file, checked against the dataclass ``cls``."""
    types = {f.name: f.type for f in fields(cls)}
    values = {}
    for key, value in given.items():
        if key not in types:
            raise ValueError(f"{where}: {section}.{key} is not a field of {section}{_did_you_mean(key, list(types))} "
                             f"(fields: {', '.join(types)})")
        values[key] = _field_value(where, f"{section}.{key}", value, str(types[key]))
    return values


def _field_value(where: str, field_name: str, value: Any, kind: str) -> Any:
    """``value`` from JSON as the dataclass field of annotation ``kind`` holds it (lists become tuples)."""
    def number(v: Any, integer: bool) -> bool:  # finite, and within any size a preset holds (no overflow later)
        return (not isinstance(v, bool) and isinstance(v, int if integer else (int, float))
                and math.isfinite(v) and abs(v) <= MAX_PRESET_NUMBER)

    ok = {"bool": isinstance(value, bool), "int": number(value, True), "float": number(value, False),
          "str": isinstance(value, str)}.get(kind)
    if ok is None:  # a tuple, or "int | tuple[int, ...]"
        integer = "float" not in kind
        items = value if isinstance(value, list) else None
        length = kind.count(",") + 1 if "..." not in kind else None
        ok = ((items is not None and all(number(v, integer) for v in items) and len(items) == (length or len(items))
               and len(items) > 0) or (kind.startswith("int |") and number(value, True)))
    if not ok:
        raise ValueError(f"{where}: {field_name} is {json.dumps(value)}, not a value of type {kind}")
    if kind == "float":
        return float(value)
    return _tuples(value)


def _did_you_mean(key: str, choices: list[str]) -> str:
    """`` (did you mean 'x_max'?)`` for a near miss among ``choices``, else nothing."""
    close = difflib.get_close_matches(key, choices, n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


def _check_not_registered(where: str, preset: Preset) -> None:
    """A file's preset may not take a registered preset's name with another configuration: checkpoints and
    manifests identify a preset by its name, and export would read the registered one's definition."""
    try:
        registered = registered_preset(preset.name)
    except ValueError:
        return
    if registered != preset:
        raise ValueError(f"{where}: name {preset.name!r} is a registered preset's, whose configuration differs; "
                         "give this one a name of its own")


def preset_fields(config: dict) -> dict[str, object]:
    """A preset's ``to_dict()`` as ``{"name": "edge", "bev.x_max": 70.4, …}``, the values as JSON holds them
    (tuples and lists alike): two presets compared field by field, a difference named by its field."""
    fields: dict[str, object] = {}
    for key, value in json.loads(json.dumps(config)).items():
        if isinstance(value, dict):
            fields.update({f"{key}.{field}": inner for field, inner in value.items()})
        else:
            fields[key] = value
    return fields


def check_preset(preset: Preset) -> None:
    """ValueError naming each field of ``preset`` the networks or the pipeline cannot run as meant, with a value
    that would do; run on every preset taken by name or file for training and export (:func:`get_preset`).

    - the grid is a whole number of cells along x and y, and of PIXOR's output cells (its maps are the grid /
      output_stride, and decoding reads them cell for cell);
    - the height range is a whole number of z_cell slices (``nz`` rounds: 3.5 m of 0.2 m slices became 18
      slices up to 1.1 m without a word);
    - the depth net's input is the crop scaled by input_scale (the calibration is scaled by input_scale: an
      input of another shape stretches the image, and the sparse depth and pseudo points miss it);
    - each side of the prefill kernel is odd (a max-pool centred on its pixel).
    """
    grid, stride = preset.bev, preset.pixor.output_stride
    sizes = {"bev.cell": grid.cell, "bev.z_cell": grid.z_cell, "pixor.output_stride": stride, "depth.input_scale":
             preset.depth.input_scale}
    bad = [f"{key} {value} must be positive" for key, value in sizes.items() if not value > 0]
    bad += [f"bev.{axis}_max {_metres(getattr(grid, axis + '_max'))} must be above {axis}_min "
            f"{_metres(getattr(grid, axis + '_min'))}"
            for axis in "xyz" if not getattr(grid, axis + "_max") > getattr(grid, axis + "_min")]
    if bad:  # the checks below divide by these
        raise ValueError(f"preset {preset.name!r}: {'; '.join(bad)}")
    problems = _grid_problems(grid, stride) + _pixor_problems(preset.pixor)
    wanted_hw = tuple(round(side * preset.depth.input_scale) for side in preset.crop_hw)
    if tuple(preset.depth.input_hw) != wanted_hw:
        problems.append(f"depth.input_hw {list(preset.depth.input_hw)} is not crop_hw {list(preset.crop_hw)} × "
                        f"input_scale {preset.depth.input_scale:g} (the calibration is scaled by input_scale: the "
                        f"image would be stretched off the sparse depth and pseudo points): input_hw {list(wanted_hw)}")
    decode = preset.decode
    problems += [f"decode.{name} {value!r} must lie in [0, 1]" for name, value in
                 (("score_threshold", decode.score_threshold), ("nms_iou", decode.nms_iou)) if not 0 <= value <= 1]
    problems += [f"decode.{name} has {len(value)} values: one per regression channel, 6 (cos θ, sin θ, dx, dy, "
                 "log w, log l)" for name, value in (("reg_mean", decode.reg_mean), ("reg_std", decode.reg_std))
                 if len(value) != 6]
    if decode.reg_std and min(decode.reg_std) <= 0:
        problems.append(f"decode.reg_std {list(decode.reg_std)} must be positive")
    problems += [f"{section}.{name} {value!r} must be at least {least}" for section, name, value, least in (
        ("decode", "max_candidates", decode.max_candidates, 1), ("decode", "max_detections", decode.max_detections, 1),
        ("decode", "pseudo_stride", decode.pseudo_stride, 1), ("pixor", "stem_channels", preset.pixor.stem_channels, 1),
    ) if value < least]
    problems += [f"{name} {list(value)} must be positive" for name, value in (
        ("crop_hw", preset.crop_hw), ("depth.input_hw", preset.depth.input_hw),
        ("pixor.stage_widths", preset.pixor.stage_widths), ("depth.encoder_widths", preset.depth.encoder_widths),
    ) if min(value) <= 0]
    if preset.depth.refine_mode not in REFINE_MODES:
        problems.append(f"depth.refine_mode {preset.depth.refine_mode!r} is none of {', '.join(REFINE_MODES)}")
    kernel = tuple(preset.depth.prefill_kernel)
    if any(side < 1 or side % 2 == 0 for side in kernel):
        odd = [max(1, side + (side % 2 == 0)) for side in kernel]
        problems.append(f"depth.prefill_kernel {list(kernel)} must be odd on each side (a max-pool centred on its "
                        f"pixel): prefill_kernel {odd}")
    if problems:
        raise ValueError(f"preset {preset.name!r}: {'; '.join(problems)}")


def _pixor_problems(pixor: PixorConfig) -> list[str]:
    """What :func:`check_preset` says of an output stride PIXOR has no stage for, or of FPN widths that are not one
    per level (the model build would refuse both, but only where torch runs, after the file was accepted)."""
    strides = PIXOR_STAGE_STRIDES[:-1]
    if pixor.output_stride not in strides:
        return [f"pixor.output_stride {pixor.output_stride} is none of PIXOR's stage strides "
                + ", ".join(map(str, strides))]
    levels = len(PIXOR_STAGE_STRIDES) - PIXOR_STAGE_STRIDES.index(pixor.output_stride)
    widths = (pixor.fpn_channels,) if isinstance(pixor.fpn_channels, int) else tuple(pixor.fpn_channels)
    shown = pixor.fpn_channels if isinstance(pixor.fpn_channels, int) else list(widths)
    if not isinstance(pixor.fpn_channels, int) and len(widths) != levels:
        return [f"pixor.fpn_channels {shown} gives {len(widths)} width{'s' * (len(widths) != 1)}, but an output stride of "
                f"{pixor.output_stride} has {levels} FPN levels (up to /{PIXOR_STAGE_STRIDES[-1]}): one width per "
                + "level, or a single number"]
    return [f"pixor.fpn_channels {shown} must be positive"] if min(widths) <= 0 else []


def _grid_problems(grid: BevGrid, stride: int) -> list[str]:
    """What :func:`check_preset` says of a grid that is not whole cells (x, y), slices (z) or output cells, each
    with the maximum that makes it so while keeping the range asked for."""
    problems = []
    for axis, cell, count, multiple in (("x", grid.cell, "nx", stride), ("y", grid.cell, "ny", stride),
                                        ("z", grid.z_cell, "nz", 1)):
        low, high = getattr(grid, f"{axis}_min"), getattr(grid, f"{axis}_max")
        cells = (high - low) / cell
        if abs(cells - round(cells)) < 1e-6 and round(cells) % multiple == 0:
            continue
        fixed = math.ceil(cells / multiple - 1e-6) * multiple
        unit = f"z_cell {_metres(cell)}" if axis == "z" else f"cell {_metres(cell)}"
        unit += f" with {axis}_min {_metres(low)}" if axis != "x" or low != 0 else ""
        whole = abs(cells - round(cells)) < 1e-6
        what = (f"gives {count} {round(cells)}, not a multiple of the output stride {stride}" if whole else
                f"is {cells:.4g} {'slices' if axis == 'z' else 'cells'}, not a whole number (rounded to {count} "
                f"{getattr(grid, count)}, up to {_metres(low + getattr(grid, count) * cell)})")
        problems.append(f"bev.{axis}_max {_metres(high)} at {unit} {what}: {axis}_max {_metres(low + fixed * cell)} "
                        f"gives {fixed}")
    return problems


def _metres(value: float) -> str:
    """A length as the preset writes it (70.0, 70.4), without the float's last-digit noise (70.39999999999999)."""
    return repr(round(float(value), 6))


def lidar_only(preset: Preset) -> Preset:
    """The preset a LiDAR-only PIXOR of the same grid has: ``preset`` without what only concerns the
    pseudo points (``-split``'s channels, ``-near35``'s range), so its name is that of the LiDAR rows."""
    near = "-near35" in preset.name
    if not preset.bev.split_pseudo and not near:
        return preset
    depth = replace(preset.depth, max_depth=DepthNetConfig.max_depth) if near else preset.depth
    return replace(preset, name=preset.name.replace("-split", "").replace("-near35", ""), depth=depth,
                   bev=replace(preset.bev, split_pseudo=False))


def _tuples(value: Any) -> Any:
    """JSON lists back to the tuples the frozen dataclasses hold."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def preset_from_dict(config: dict) -> Preset:
    """Rebuild a :class:`Preset` from its ``to_dict()`` form (as stored in a model manifest)."""
    try:
        return Preset(
            name=config["name"],
            depth=DepthNetConfig(**{k: _tuples(v) for k, v in config["depth"].items()}),
            pixor=PixorConfig(**{k: _tuples(v) for k, v in config["pixor"].items()}),
            bev=BevGrid(**config["bev"]),
            decode=DecodeConfig(**{k: _tuples(v) for k, v in config["decode"].items()}),
            crop_hw=_tuples(config["crop_hw"]),
        )
    except (KeyError, TypeError) as exc:
        raise ValueError(f"preset configuration does not match this version of lowres3d ({exc})") from exc
