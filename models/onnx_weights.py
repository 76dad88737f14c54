"""The weights of an exported ONNX network, loaded back into its PyTorch twin.

The shipped model directories hold ONNX files, not training checkpoints, yet
``benchmarks/latency.py --compare-torch`` is to time PyTorch eager with the
same weights. The exported graphs differ from the PyTorch networks only by
exact rewrites, and each is undone here exactly:

- torch.onnx folds every batch norm into the convolution before it
  (``<conv>.weight`` scaled, plus ``<conv>.weight_bias``): the conv takes the
  folded weight and its batch norm becomes the identity that adds the folded bias;
- export.rewrite's lowering (:func:`export.rewrite.lower_for_cpu`): merged parallel
  convs are cut back out of their block-diagonal weight, an input conv split in
  two is concatenated again, narrow convs padded with zero channels are sliced
  back, a stride-1 transposed conv written as a conv gets its kernel
  flipped and its channel axes swapped back, and merged output heads are cut
  apart along their output channels.

Every parameter and batch-norm statistic of the network must be accounted for,
and :func:`load_onnx_weights` is meant to be followed by the exporter's parity
check against ONNX Runtime, which :func:`benchmarks.latency.torch_twin` runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.cli import ctrl_c_held_while_loading

with ctrl_c_held_while_loading(__name__ == "__main__"):  # ONNX, after PyTorch (models/__init__.py)
    import numpy as np
    import onnx
    import torch
    from onnx import numpy_helper
    from torch import nn


def _batch_norm_after(name: str, modules: dict[str, nn.Module]) -> str | None:
    """The batch norm that follows conv ``name`` (``x.0`` → ``x.1``, ``conv2`` → ``bn2``), if any."""
    parent, _, child = name.rpartition(".")
    prefix = f"{parent}." if parent else ""
    if child.isdigit():
        candidate = f"{prefix}{int(child) + 1}"
    elif child.startswith("conv") and child[4:].isdigit():
        candidate = f"{prefix}bn{child[4:]}"
    else:
        return None
    return candidate if isinstance(modules.get(candidate), nn.BatchNorm2d) else None


def _unlowered(graph: onnx.GraphProto, arrays: dict[str, np.ndarray], convs: dict[str, nn.Module]) -> dict:
    """Weights (and biases) of the convs that export.rewrite renamed, keyed ``<conv>.weight`` / ``.weight_bias``."""
    found: dict[str, np.ndarray] = {}
    missing = [name for name in convs if f"{name}.weight" not in arrays]
    nodes = {node.name: node for node in graph.node}
    for node in graph.node:
        if node.op_type != "Conv":
            continue
        weight, bias = node.input[1], node.input[2] if len(node.input) > 2 else ""
        if weight.endswith("_merged_w"):  # merge_parallel_convs: block-diagonal, branches in Concat order
            concat = nodes[weight[: -len("_w")] + "_inputs"]
            w, b = arrays[weight], arrays[bias]
            rows = cols = 0
            branches = [n for n in missing if isinstance(convs[n], nn.Conv2d)][: len(concat.input)]
            for name in branches:
                out_ch, in_ch = convs[name].weight.shape[:2]
                found[f"{name}.weight"] = w[rows : rows + out_ch, cols : cols + in_ch]
                found[f"{name}.weight_bias"] = b[rows : rows + out_ch]
                rows, cols = rows + out_ch, cols + in_ch
            if (rows, cols) != w.shape[:2]:
                raise ValueError(f"{weight}: {w.shape} is not the block-diagonal of {', '.join(branches)}")
            missing = [n for n in missing if n not in branches]
        elif weight.endswith("_heads_w"):  # merge_output_heads: the heads' output channels side by side, in order
            w, b = arrays[weight], arrays[bias]
            sizes = [int(n) for n in arrays[weight[: -len("_w")] + "_sizes"]]
            alike = [n for n in missing if isinstance(convs[n], nn.Conv2d) and convs[n].weight.shape[1:] == w.shape[1:]]
            heads = next((alike[i : i + len(sizes)] for i in range(len(alike))
                          if [convs[n].weight.shape[0] for n in alike[i : i + len(sizes)]] == sizes), None)
            if heads is None:
                raise ValueError(f"{weight}: the network has no {len(sizes)} convs of {sizes} channels it could belong to")
            rows = 0
            for name, size in zip(heads, sizes, strict=True):
                found[f"{name}.weight"] = w[rows : rows + size]
                found[f"{name}.weight_bias"] = b[rows : rows + size]
                rows += size
            missing = [n for n in missing if n not in heads]
        elif weight.startswith("node_ConvTranspose_") and weight.endswith("_w"):  # a stride-1 transposed conv
            name = next((n for n in missing if isinstance(convs[n], nn.ConvTranspose2d) and convs[n].stride == (1, 1)),
                        None)
            if name is None:
                raise ValueError(f"{weight}: the network has no stride-1 transposed conv it could belong to")
            found[f"{name}.weight"] = np.ascontiguousarray(np.flip(arrays[weight], (2, 3)).transpose(1, 0, 2, 3))
            found[f"{name}.weight_bias"] = arrays[bias]
            missing.remove(name)
    for node in graph.node:  # split_input_convs: two convs on slices of one input, summed
        if node.op_type == "Conv" and node.input[1].endswith("_wa"):
            stem = node.input[1][: -len("_wa")]
            whole = np.concatenate([arrays[f"{stem}_wa"], arrays[f"{stem}_wb"]], axis=1)
            name = next((n for n in missing if tuple(convs[n].weight.shape) == whole.shape), None)
            if name is None:
                raise ValueError(f"{stem}: the network has no conv of shape {whole.shape} it could belong to")
            found[f"{name}.weight"] = whole
            missing.remove(name)
    if missing:
        raise ValueError(f"no weights in the graph for {', '.join(missing)}")
    return found


def _under(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(f"{p}.") for p in prefixes)


def _absent(graph: onnx.GraphProto, prefixes: tuple[str, ...]) -> tuple[str, ...]:
    """The submodules among ``prefixes`` of which the graph has no node and no weight."""
    names = [init.name for init in graph.initializer] + [node.name.lstrip("/").replace("/", ".") for node in graph.node]
    return tuple(p for p in prefixes if not any(_under(n, (p,)) for n in names))


def read_onnx(path: str | Path, load_external_data: bool = True) -> onnx.ModelProto:
    """An ONNX file, or a ValueError naming it when it is not one (onnx.load raises protobuf's DecodeError for
    a truncated or foreign file, which is no error a user should read as a trace)."""
    try:
        return onnx.load(str(path), load_external_data=load_external_data)
    except OSError:
        raise
    except Exception as exc:  # google.protobuf.message.DecodeError and friends
        raise ValueError(f"{path}: not a readable ONNX model ({type(exc).__name__}: {exc})") from exc


def load_onnx_weights(network: nn.Module, path: str | Path, optional: tuple[str, ...] = ()) -> tuple[str, ...]:
    """Set every parameter and batch-norm buffer of ``network`` from the exported graph at ``path``.

    optional: submodules (``refine``, say) the graph may lack: if it has none of their nodes and
    weights they keep the network's own values, so a network with a head added since the export
    can start from the exported weights. Returns those left as they were.
    Raises ValueError when the graph does not hold this network's weights (another preset, say).
    """
    model = read_onnx(path)
    if any(node.op_type == "DequantizeLinear" for node in model.graph.node):
        raise ValueError(f"{path}: an INT8 (quantized) graph, whose weights cannot be read back as trained; "
                         "give the FP32 model directory it was converted from (its manifest's precision_info.source)")
    arrays = {init.name: numpy_helper.to_array(init) for init in model.graph.initializer}
    leave = _absent(model.graph, optional)
    modules = {name: m for name, m in network.named_modules() if not _under(name, leave)}
    convs = {name: m for name, m in modules.items() if isinstance(m, nn.Conv2d | nn.ConvTranspose2d)}
    try:
        arrays.update(_unlowered(model.graph, arrays, convs))
    except (ValueError, KeyError) as exc:
        raise ValueError(f"{path}: not this network's graph ({exc})") from exc
    state: dict[str, torch.Tensor] = {}

    def put(key: str, value: np.ndarray, like: torch.Tensor) -> None:
        # Narrow convs padded with zero channels (pad_narrow_convs) are cut back to the network's shape; anything
        # non-zero beyond it is no padding but weights of another network (a taller grid's PIXOR, say), which
        # cut to this shape would run with some of its weights gone and the rest on the wrong channels.
        cut = value[tuple(slice(0, n) for n in like.shape)]
        if cut.shape != tuple(like.shape):
            raise ValueError(f"{path}: {key} has shape {value.shape}, the network's is {tuple(like.shape)}")
        if cut.size != value.size and np.count_nonzero(value) != np.count_nonzero(cut):
            raise ValueError(f"{path}: {key} has shape {value.shape}, the network's is {tuple(like.shape)}, and "
                             "what lies beyond it is not the exporter's zero padding (a network of another preset?)")
        value = cut
        state[key] = torch.from_numpy(np.array(value, dtype=np.float32)).to(like.dtype)  # a writable copy

    reference = network.state_dict()
    for name, conv in convs.items():
        put(f"{name}.weight", arrays[f"{name}.weight"], conv.weight)
        # A bias the graph does not have is zero: the exporter's optimizer drops all-zero biases.
        folded = arrays.get(f"{name}.weight_bias")
        norm = _batch_norm_after(name, modules)
        if norm is not None and f"{norm}.running_mean" not in arrays:  # folded into the conv
            bn = modules[norm]
            put(f"{norm}.weight", np.ones(bn.num_features, np.float32), bn.weight)
            put(f"{norm}.bias", np.zeros(bn.num_features, np.float32) if folded is None else folded, bn.bias)
            put(f"{norm}.running_mean", np.zeros(bn.num_features, np.float32), bn.running_mean)
            # 1 / sqrt(var + eps) = 1 exactly enough: var = 1 − eps rounds to within one float32 step.
            put(f"{norm}.running_var", np.full(bn.num_features, 1.0 - bn.eps, np.float32), bn.running_var)
            state[f"{norm}.num_batches_tracked"] = reference[f"{norm}.num_batches_tracked"]
        elif conv.bias is not None:
            bias = arrays.get(f"{name}.bias", folded)
            put(f"{name}.bias", np.zeros(conv.bias.shape[0], np.float32) if bias is None else bias, conv.bias)
    for key, value in reference.items():  # anything else (a GAM's own conv, say) by its own name
        if _under(key.rpartition(".")[0], leave):
            state[key] = value
        elif key not in state and key in arrays:
            put(key, arrays[key], value)
        elif key not in state and key.endswith(".num_batches_tracked"):
            # A count of training batches, no weight: no graph holds it, so a batch norm the graph keeps
            # unfolded (its statistics read by name above) keeps the network's own count.
            state[key] = value
    unset = [key for key in reference if key not in state]
    if unset:
        raise ValueError(f"{path}: no weights for {', '.join(unset[:6])}{' …' if len(unset) > 6 else ''}")
    network.load_state_dict(state, strict=True)
    return leave


def refuse_held_checkpoints(out: Path) -> None:
    """InputError naming --out when ``out`` holds checkpoints already: a training run's own (or another
    conversion's) are never replaced."""
    from models.checkpoint import CHECKPOINT_FILES
    from pipeline.errors import InputError

    held = [name for name in (*CHECKPOINT_FILES.values(), "state.pt") if (Path(out) / name).exists()]
    if held:
        raise InputError(f"--out {out}: already holds {' and '.join(held)}; give a new folder")


def checkpoints_from_model_dir(models: str | Path, out: str | Path) -> dict[str, Path]:
    """Write ``depth.pt`` / ``pixor.pt`` checkpoints (models/checkpoint.py) of a model directory's ONNX files.

    Each checkpoint carries the manifest's preset and the network's training record, so
    ``python -m export --checkpoints OUT`` re-exports it and training can start from it. The batch norms
    come folded (identity statistics): fine-tune such weights with ``--train-only`` or batch norms in eval mode.
    """
    from models import build_network
    from models.checkpoint import CHECKPOINT_FILES, save_checkpoint
    from pipeline.model_files import load_manifest, verify_sha256
    from pipeline.presets import preset_from_dict

    models, out = Path(models), Path(out)
    refuse_held_checkpoints(out)
    manifest = load_manifest(models)
    verify_sha256(models, manifest)  # a damaged or edited ONNX file is named as such, as the runtime names it
    preset = preset_from_dict(manifest["preset_config"])
    written = {}
    for name, entry in manifest["networks"].items():
        net = build_network(name, preset).eval()
        load_onnx_weights(net, models / entry["file"])
        metadata = {**(entry.get("training") or {}), "from_onnx": str(models / entry["file"])}
        written[name] = save_checkpoint(out / CHECKPOINT_FILES[name], preset, {name: net}, metadata)
    return written


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m models.onnx_weights``."""
    from pipeline.cli import HelpFormatter, examples

    parser = argparse.ArgumentParser(
        allow_abbrev=False,  # a prefix is no flag: --frame is not --frames
        prog="python -m models.onnx_weights", formatter_class=HelpFormatter,
        description="Turn a model directory's ONNX files back into training checkpoints (depth.pt, pixor.pt).",
        epilog=examples("python -m models.onnx_weights --models weights/edge --out runs/own/camera"))
    parser.add_argument("--models", type=Path, required=True, metavar="DIR",
                        help="model directory (manifest.json and ONNX files)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="checkpoint directory to write")
    return parser


def main(argv: list[str] | None = None) -> int:
    import sys

    from pipeline.cli import check_not_input, check_output, quiet_interrupt
    from pipeline.errors import InputError
    from pipeline.model_files import ModelFileError

    @quiet_interrupt("--out holds what was written before it (a checkpoint is written whole or not at all)")
    def run(args: argparse.Namespace) -> int:
        try:  # what is wrong with --out, named as --out (not as --models, the conversion's errors below)
            check_output(args.out, "--out", directory=True)
            check_not_input(args.out, "--out", {"--models": args.models})
            refuse_held_checkpoints(args.out)
        except InputError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        try:
            written = checkpoints_from_model_dir(args.models, args.out)
        except (InputError, OSError, ValueError, KeyError, ModelFileError) as exc:
            print(f"error: --models: {exc}", file=sys.stderr)
            return 2
        print("wrote " + ", ".join(str(path) for path in written.values()))
        return 0

    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
