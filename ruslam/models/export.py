"""UWNet weight files: fp16 weights-only export from a Lightning checkpoint, loading with clear errors, ONNX.

A weights file is a plain dict readable with ``torch.load(..., weights_only=True)``:
``{"format": "ruslam-uwnet", "version": 1, "config": UWNet kwargs, "state_dict": fp16 tensors}``; no pickled
classes, no optimizer state, so it stays a few MB and is safe to load.

CLI: ``python -m ruslam.models.export CHECKPOINT.ckpt OUT.pt [--teacher-detector] [--no-descriptor-residual]
[--onnx OUT.onnx --height 480 --width 640]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from ruslam.atomic_files import atomic_path
from ruslam.errors import InputError, MissingWeights
from ruslam.models.uwnet import UWNet

FORMAT = "ruslam-uwnet"
VERSION = 1


def _atomic_save(obj, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _load(path: Path) -> dict:
    if not path.is_file():
        raise MissingWeights(f"UWNet weights file {path} does not exist.")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 (any unreadable/unsafe file gets one sentence)
        raise InputError(f"{path} is not a readable weights-only torch file ({type(err).__name__}).") from None
    if not isinstance(obj, dict):
        raise InputError(f"{path} does not hold a dict of weights (got {type(obj).__name__}).")
    return obj


def lightning_to_payload(ckpt_path: str | Path) -> dict:
    """The UWNet part of a `DistillationModule` Lightning checkpoint as an fp16 weights-only payload."""
    path = Path(ckpt_path)
    ckpt = _load(path)
    if "uwnet_config" not in ckpt or "state_dict" not in ckpt:
        raise InputError(f"{path} is not a DistillationModule checkpoint (no 'uwnet_config'/'state_dict').")
    state = {k[len("net."):]: v for k, v in ckpt["state_dict"].items() if k.startswith("net.")}
    return _payload(dict(ckpt["uwnet_config"]), state)


def _payload(config: dict, state: dict) -> dict:
    half = {k: (v.half() if v.is_floating_point() else v).contiguous() for k, v in state.items()}
    return {"format": FORMAT, "version": VERSION, "config": config, "state_dict": half}


def build_network(config: dict) -> torch.nn.Module:
    """The student network a weights file's config describes: ``architecture`` "xfeat_student" is the XFeat student
    (`XFeatStudent`), absent is the paper's MobileNetV2 UWNet."""
    config = dict(config)
    arch = config.pop("architecture", "uwnet")
    if arch == "xfeat_student":
        from ruslam.models.uwnet_xfeat_student import XFeatStudent  # noqa: PLC0415

        return XFeatStudent(**config, teacher_weights="none")
    if arch != "uwnet":
        raise InputError(f"weights config names an unknown architecture {arch!r}; expected 'uwnet' or 'xfeat_student'.")
    return UWNet(**config)


def export_weights(source: torch.nn.Module | str | Path, out_path: str | Path) -> Path:
    """Write an fp16 weights file from a student network or a Lightning checkpoint path (temp file + rename)."""
    if isinstance(source, torch.nn.Module):
        payload = _payload(dict(source.config), source.state_dict())
    else:
        payload = lightning_to_payload(source)
    out = Path(out_path)
    _atomic_save(payload, out)
    return out


def load_uwnet(path: str | Path, descriptor_dim: int | None = None) -> torch.nn.Module:
    """Rebuild a UWNet (float32, eval mode) from an exported weights file or a DistillationModule checkpoint."""
    path = Path(path)
    obj = _load(path)
    if "uwnet_config" in obj:  # a Lightning checkpoint straight from training
        obj = lightning_to_payload(path)
    if obj.get("format") != FORMAT or "config" not in obj or "state_dict" not in obj:
        raise InputError(f"{path} is not a UWNet weights file (expected format {FORMAT!r}); export one with "
                         f"`python -m ruslam.models.export CHECKPOINT OUT.pt`.")
    config = dict(obj["config"])
    if descriptor_dim is not None and config.get("descriptor_dim") != descriptor_dim:
        raise InputError(f"{path} has {config.get('descriptor_dim')}-d descriptors, but {descriptor_dim}-d were "
                         f"requested.")
    try:
        net = build_network(config)
    except TypeError as err:
        raise InputError(f"{path} holds an unknown UWNet configuration ({err}).") from None
    own = net.state_dict()
    state = obj["state_dict"]
    missing, unexpected = sorted(set(own) - set(state)), sorted(set(state) - set(own))
    wrong = [k for k in own if k in state and own[k].shape != state[k].shape]
    if missing or unexpected or wrong:
        first = (missing or unexpected or wrong)[0]
        raise InputError(f"{path} does not match the UWNet architecture of its config (first mismatch: {first}).")
    net.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()})
    return net.eval()


class _TupleOutputs(torch.nn.Module):
    def __init__(self, net: UWNet):
        super().__init__()
        self.net = net

    def forward(self, image):
        out = self.net(image)
        return out["keypoint_logits"], out["dense_descriptors"], out["global_descriptor"]


ONNX_OUTPUTS = ("keypoint_logits", "dense_descriptors", "global_descriptor")


def export_onnx(net: UWNet, path: str | Path, height: int = 480, width: int = 640, opset: int = 17) -> Path:
    """ONNX graph of the inference path (DCNs via the grid_sample fast path) for a fixed HxW, dynamic batch."""
    path = Path(path)
    wrapper = _TupleOutputs(net).eval()  # export restores the wrapper's mode recursively: keep it eval
    dummy = torch.rand(1, 3, height, width)
    with torch.no_grad(), atomic_path(path) as tmp:
        torch.onnx.export(wrapper, (dummy,), str(tmp), input_names=["image"], output_names=list(ONNX_OUTPUTS),
                          opset_version=opset, dynamic_axes={"image": {0: "batch"}}, dynamo=False)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Export UWNet weights (fp16, weights only) and optionally ONNX.")
    parser.add_argument("checkpoint", help="DistillationModule Lightning checkpoint (.ckpt) or a weights file")
    parser.add_argument("out", help="output weights file (.pt)")
    parser.add_argument("--onnx", help="also write an ONNX graph here")
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--teacher-detector", action="store_true",
                        help="XFeat student only: put XFeat's own keypoint branch back (no attention), keep the rest")
    parser.add_argument("--no-descriptor-residual", action="store_true",
                        help="XFeat student only: drop the residual block (two DCNs) of the descriptor branch")
    args = parser.parse_args(argv)
    net = load_uwnet(args.checkpoint)
    if args.teacher_detector or args.no_descriptor_residual:
        from ruslam.models import uwnet_xfeat_student as student  # noqa: PLC0415

        if not isinstance(net, student.XFeatStudent):
            raise SystemExit(f"{args.checkpoint} is not an XFeat student: --teacher-detector and "
                             f"--no-descriptor-residual apply to the XFeat student only.")
        if args.teacher_detector:
            net = student.with_teacher_detector(net).eval()
        if args.no_descriptor_residual:
            net = student.without_descriptor_residual(net).eval()
    out = export_weights(net, args.out)
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB)")
    if args.onnx:
        print(f"wrote {export_onnx(net, args.onnx, args.height, args.width)}")


if __name__ == "__main__":
    main()
