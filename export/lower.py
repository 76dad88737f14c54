"""Re-apply the current CPU lowering to an existing FP32 model directory, without its checkpoints.

    python -m export.lower --models DIR [--out DIR] [--data DIR --frame ID]

The exporter lowers every graph it traces (``export.rewrite.lower_for_cpu``),
but a directory exported before a rewrite existed keeps its older graphs, and
shipped weights come without their training checkpoints. The rewrites are
exact graph transformations, so they can be applied to the ONNX files
themselves: this command does that, checks ONNX Runtime's outputs of the new
graphs against the old ones on a real KITTI frame and on random inputs, and
rewrites the manifest's sha256s, ``graph_inputs`` and ``export.cpu_rewrites``. Applying it twice
changes nothing (every rewrite skips what it already lowered, and a directory
with nothing left to rewrite is not touched).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from export.directory import check_destination, staged
from export.inputs import DEFAULT_FRAME, DEFAULT_KITTI_DIR, check_frame, kitti_inputs, random_inputs
from export.manifest import graph_inputs, write_manifest
from export.rewrite import lower_for_cpu
from pipeline.cli import HelpFormatter, check_not_inside, examples, interrupted
from pipeline.graph_inputs import feeds_for
from pipeline.model_files import MANIFEST_NAME, ModelFileError, load_manifest, sha256_file, verify_sha256
from pipeline.presets import preset_from_dict

TOLERANCE = 1e-5  # absolute and relative: the rewrites are exact up to float summation order


@dataclass
class LowerResult:
    """What :func:`run` changed: rewrites per network and the largest output difference it measured."""

    directory: Path
    rewrites: dict[str, dict[str, int]]
    max_abs_difference: dict[str, float]
    written: bool = True  # False: rewritten in place with nothing to rewrite, so left as it was


def run(models: Path, out: Path | None = None, data: Path = DEFAULT_KITTI_DIR,
        frame: str = DEFAULT_FRAME) -> LowerResult:
    """Lower the graphs of ``models`` into ``out`` (default: in place); returns what changed.

    The real frame of the check is ``frame`` of the KITTI object folder ``data`` (default: the bundled
    tests/data frame, which only a source checkout has). Raises InputError when that frame is missing,
    ModelFileError for a directory that is not an intact FP32 model directory (or an ``out``
    that holds something else), and ValueError when ONNX Runtime's outputs of a lowered graph differ
    from the original past :data:`TOLERANCE`; nothing is written then.
    """
    models = Path(models)
    out = models if out is None else Path(out)
    check_frame(data, frame)  # before any model work; names --data/--frame
    manifest = load_manifest(models)
    verify_sha256(models, manifest)
    if manifest.get("precision", "fp32") != "fp32":
        raise ModelFileError(f"{models / MANIFEST_NAME}: precision {manifest['precision']}; lower the FP32 "
                             "directory and convert it again (python -m export.precision)")
    preset = preset_from_dict(manifest["preset_config"])
    samples = [kitti_inputs(preset, data, frame), random_inputs(preset, seed=1)]
    sources: dict[str, onnx.ModelProto] = {}
    lowered: dict[str, onnx.ModelProto] = {}
    rewrites: dict[str, dict[str, int]] = {}
    differences: dict[str, float] = {}
    for name, entry in manifest["networks"].items():
        source = onnx.load(str(models / entry["file"]))
        graph, counts = lower_for_cpu(source)
        onnx.checker.check_model(graph, full_check=True)
        before, after = (ort.InferenceSession(g.SerializeToString(), providers=["CPUExecutionProvider"])
                         for g in (source, graph))
        worst = 0.0
        for sample in samples:
            feeds = sample.feeds(name)
            for a, b in zip(before.run(None, feeds_for(before, feeds)), after.run(None, feeds_for(after, feeds)),
                            strict=True):
                if not np.allclose(b, a, rtol=TOLERANCE, atol=TOLERANCE):
                    raise ValueError(f"{models / entry['file']}: the lowered graph differs from the original by "
                                     f"{float(np.max(np.abs(a - b))):.3g} on {sample.source}")
                worst = max(worst, float(np.max(np.abs(a - b))))
        sources[name], lowered[name], rewrites[name], differences[name] = source, graph, counts, worst

    in_place = out.resolve() == models.resolve()
    listed = all(manifest["networks"][name].get("graph_inputs") == graph_inputs(source)
                 for name, source in sources.items())
    if in_place and listed and not any(any(counts.values()) for counts in rewrites.values()):
        return LowerResult(out, rewrites, differences, written=False)  # already lowered: left as it is
    if not in_place:
        check_destination(out, manifest.get("preset"), manifest.get("precision", "fp32"))

    # Everything is written into a staging copy first and swapped in at the end (export.directory).
    with staged(out, source=models) as staging:
        recorded = manifest.setdefault("export", {}).setdefault("cpu_rewrites", {})
        for name, graph in lowered.items():
            path = staging / manifest["networks"][name]["file"]
            onnx.save(graph, str(path))
            manifest["files"][path.name] = {"sha256": sha256_file(path), "bytes": path.stat().st_size}
            manifest["networks"][name]["graph_inputs"] = graph_inputs(graph)
            totals = recorded.setdefault(name, {})
            for rewrite, count in rewrites[name].items():
                totals[rewrite] = totals.get(rewrite, 0) + count
        manifest["export"]["relowered"] = {"by": "python -m export.lower", "max_abs_difference": differences,
                                           "checked_on": [sample.source for sample in samples]}
        write_manifest(staging, manifest)
        verify_sha256(staging, manifest)
    return LowerResult(out, rewrites, differences)


def main(argv: list[str] | None = None) -> int:
    epilog = __doc__.split("\n\n", 1)[1] + "\n" + examples(
        "python -m export.lower --models weights/own --out weights/own-relowered")
    parser = argparse.ArgumentParser(allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
                                     prog="python -m export.lower", description=__doc__.split("\n\n")[0],
                                     epilog=epilog, formatter_class=HelpFormatter)
    parser.add_argument("--models", type=Path, required=True, metavar="DIR",
                        help="FP32 model directory (manifest.json + ONNX files)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="output model directory (default: rewrite --models in place)")
    parser.add_argument("--data", type=Path, default=None, metavar="DIR",
                        help="KITTI object folder (image_2/, velodyne/, calib/) of the real frame the new graphs are "
                        "checked on (default: the bundled tests/data/kitti/training of a source checkout)")
    parser.add_argument("--frame", default=DEFAULT_FRAME, metavar="ID", help=f"frame id of --data (default {DEFAULT_FRAME})")
    args = parser.parse_args(argv)
    if args.data is None and not DEFAULT_KITTI_DIR.is_dir():  # installed from a wheel: tests/data stayed behind
        print(f"error: the bundled check frames ({DEFAULT_KITTI_DIR}) exist only in a source checkout; give a "
              "KITTI object folder with --data DIR (and --frame ID)", file=sys.stderr)
        return 2
    try:
        # The output directory is replaced whole once the new graphs are written: not with the check frames in it.
        check_not_inside(args.out or args.models, "--out" if args.out else "--models", {"--data": args.data})
        result = run(args.models, args.out, args.data or DEFAULT_KITTI_DIR, args.frame)
    except (ModelFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # an unwritable or full --out: the source is untouched
        print(f"error: {exc.filename or args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # the staging folder is removed; the result is swapped in only at the end
        return interrupted(f"{args.out or args.models} is as it was (nothing written)")
    for name, counts in result.rewrites.items():
        changed = ", ".join(f"{k} {v}" for k, v in counts.items() if v) or "nothing to rewrite"
        print(f"{name}: {changed}; max |difference| {result.max_abs_difference[name]:.3g}")
    print(f"wrote {result.directory}" if result.written else f"unchanged: {result.directory} (already lowered)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
