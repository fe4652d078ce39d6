"""Checks of a composed config that run before torch is imported and before any network or trainer is built.

A typo or a missing file then costs the user a second, not the minutes of building a Trainer, a teacher or a
sweep. Each entry point calls its check first (`train` -> `check_train`, `evaluate` -> the task's ``check``);
the deeper checks (a file's content, a folder's layout) stay in the readers, which the checks call when cheap.
"""

from __future__ import annotations

from pathlib import Path
from urllib.parse import urlparse

from hydra.errors import InstantiationException
from hydra.utils import get_method
from hydra.utils import instantiate as hydra_instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from ruslam.cli import input_error_of, missing_value_message
from ruslam.errors import InputError, MissingInput, MissingWeights

#: Columns of the SLAM tables (`dataset.metrics`) and their headers.
SLAM_METRICS = {"ape": "APE", "rpe": "RPE", "tracked": "Tracked", "tracked_after_init": "Tracked after init",
                "maps": "Maps", "tracked_all_maps": "In all maps", "ape_path": "APE % of path", "fps": "fps"}
SLAM_SENSORS = ("auto", "mono", "stereo")
WEIGHT_SUFFIXES = (".pt", ".pth", ".ckpt")


def missing_keys(cfg, prefix: str = "") -> list[str]:
    """Full keys of the ``???`` values, found without resolving interpolations (which would fail on them)."""
    keys = cfg.keys() if isinstance(cfg, DictConfig) else range(len(cfg))
    out = []
    for key in keys:
        if OmegaConf.is_missing(cfg, key):
            out.append(f"{prefix}{key}")
        elif not OmegaConf.is_interpolation(cfg, key) and isinstance(cfg[key], DictConfig | ListConfig):
            out += missing_keys(cfg[key], f"{prefix}{key}.")
    return out


def require_set(cfg: DictConfig) -> None:
    """Every ``???`` value is set; else the first is named with how to set it."""
    missing = missing_keys(cfg)
    if missing:
        more = f" ({len(missing) - 1} more unset: {', '.join(missing[1:])})" if len(missing) > 1 else ""
        raise InputError(missing_value_message(missing[0]) + more)


def require_path(cfg: DictConfig, key: str, kind: str, error=MissingInput) -> None:
    """The path at `key` (when set) exists as a `kind` ("file" or "folder"); URLs are left to the downloader."""
    value = OmegaConf.select(cfg, key, default=None)
    if value is None or urlparse(str(value)).scheme in ("http", "https", "file"):
        return
    path = Path(str(value)).expanduser()
    exists = path.is_dir() if kind == "folder" else path.is_file()
    if not exists:
        found = " (it is a file)" if path.is_file() else " (it is a folder)" if path.is_dir() else ""
        raise error(f"{key}={value}: no such {kind}{found}.")


def instantiate(conf):
    """`hydra.utils.instantiate`, raising a reader's InputError itself rather than Hydra's wrapper around it."""
    try:
        return hydra_instantiate(conf)
    except InstantiationException as err:
        cause = input_error_of(err)
        if cause is None:
            raise
        raise cause from None


def require_choice(key: str, values, allowed) -> None:
    unknown = [str(v) for v in values if str(v) not in allowed]
    if unknown:
        raise InputError(f"{key} has unknown value(s) {unknown}; expected some of {list(allowed)}.")


# ------------------------------------------------------------------------------------------------ training


def check_train(cfg: DictConfig) -> None:
    """`python train.py`: unset values, every file the config names, the source (opened, not read), sizes."""
    require_set(cfg)
    for key in ("ckpt_path", "init_weights"):
        require_path(cfg, key, "file", MissingWeights)
    if str(OmegaConf.select(cfg, "model.net.pretrained_path", default=None)) == "imagenet":
        from ruslam.models.imagenet import imagenet_mobilenet_v2  # noqa: PLC0415 (imports torch)

        imagenet_mobilenet_v2()  # the packaged ImageNet backbone: installed, and its sha256 right
    else:
        require_path(cfg, "model.net.pretrained_path", "file", MissingWeights)
    for key in ("teacher.local.weights", "teacher.global_head.weights"):
        require_path(cfg, key, "file", MissingWeights)
    if str(OmegaConf.select(cfg, "teacher.global_head.codebook", default=None)) != "packaged":  # shipped file
        require_path(cfg, "teacher.global_head.codebook", "file")
    dm = cfg.datamodule
    size = dm.get("image_size")
    if size is not None and (len(size) != 2 or any(int(v) % 8 or int(v) <= 0 for v in size)):
        raise InputError(f"datamodule.image_size must be [height, width], positive multiples of 8; got "
                         f"{list(size)}.")
    source = instantiate(cfg.data)  # readers check their files and layout in the constructor; nothing is read yet
    count = min(len(source), dm.limit_images) if dm.get("limit_images") else len(source)
    if dm.get("val_overrides") is None and count <= dm.val_size:
        raise InputError(f"The RGB-D source gives {count} images (datamodule.limit_images={dm.get('limit_images')}); "
                         f"it needs more than datamodule.val_size={dm.val_size}.")
    if dm.get("val_overrides") is not None:
        instantiate(OmegaConf.merge(cfg.data, dm.val_overrides))


# --------------------------------------------------------------------------------------------- evaluation


def check_evaluate(cfg: DictConfig) -> None:
    """`python evaluate.py`: unset values, then the task's own check (``task.check``)."""
    require_set(cfg)
    check = cfg.task.get("check")
    if check:
        get_method(check)(cfg)


def check_extractors(cfg: DictConfig) -> None:
    """`extractors` names registered extractors, ``task.weights`` keys or weights files that exist."""
    from ruslam.models.registry import EXTRACTORS  # noqa: PLC0415 (light: the registry imports no model)

    names = [str(n) for n in cfg.extractors]
    if not names:
        raise InputError("extractors is empty; name at least one extractor, e.g. extractors=[sift,orb].")
    weights = dict(cfg.task.get("weights") or {})
    for name in names:
        if name in weights or name in EXTRACTORS:
            continue
        if Path(name).suffix in WEIGHT_SUFFIXES:
            if not Path(name).is_file():
                raise MissingWeights(f"Extractor weights file {name} (in extractors) does not exist.")
            continue
        raise InputError(f"Unknown extractor {name!r} in extractors; expected one of "
                         f"{sorted(set(EXTRACTORS) | set(weights))} or a {'/'.join(WEIGHT_SUFFIXES)} weights file.")
    for name in weights:
        if name in names:  # null = not trained yet (skipped with a note); a path given must exist
            require_path(cfg, f"task.weights.{name}", "file", MissingWeights)


def check_matching(cfg: DictConfig) -> None:
    task = cfg.task
    check_extractors(cfg)
    thresholds = [float(t) for t in task.thresholds]
    if float(task.headline_threshold) not in thresholds:
        raise InputError(f"task.headline_threshold={float(task.headline_threshold):g} must be one of "
                         f"task.thresholds {thresholds}.")
    if int(task.max_keypoints) < 1:  # the cap is taken by score: a negative one would silently drop keypoints
        raise InputError(f"task.max_keypoints must be >= 1; got {task.max_keypoints}.")
    require_path(cfg, "dataset.root", "folder")
    target = str(cfg.dataset.get("_target_", ""))
    if target.endswith("upatches_from_folder"):  # enough images in the folder (the build itself writes files)
        from ruslam.data.upatches import list_folder_images  # noqa: PLC0415

        list_folder_images(cfg.dataset.root, cfg.dataset.get("num_images"))
    elif target.endswith("HPatches"):  # the reader checks the sequence folders in its constructor
        instantiate({k: v for k, v in OmegaConf.to_container(cfg.dataset, resolve=True).items() if k != "label"})


def check_slam(cfg: DictConfig) -> None:
    dataset = cfg.dataset
    check_extractors(cfg)
    require_choice("dataset.metrics", dataset.metrics, SLAM_METRICS)
    if dataset.get("select") and dataset.get("sequences") is not None:  # a folder's are found by the run itself
        require_choice("dataset.select", dataset.select, list(OmegaConf.to_container(dataset.sequences, resolve=True)))
    require_choice("slam.sensor", [cfg.slam.get("sensor", "auto")], SLAM_SENSORS)
    every = dataset.get("every", 1)
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise InputError(f"dataset.every must be a positive integer (keep every n-th frame), got {every!r}.")
    root = dataset.get("root")
    if root != "__embedded__" and (root is None or not Path(str(root)).is_dir()):
        where = f"dataset.root={root} is not a folder" if root else "dataset.root is not set"
        name = dataset.get("label") or dataset.name
        raise MissingInput(f"Dataset {name} not found: {where}. {dataset.download} Then pass dataset.root=<folder>.")


def check_synthesis(cfg: DictConfig) -> None:
    from ruslam.data.water import check_water_type  # noqa: PLC0415

    for water in cfg.task.grid_water_types:
        check_water_type(str(water))
    for key in ("dataset.reference", "dataset.background_light"):
        require_path(cfg, key, "folder")
    if int(cfg.dataset.num_images) < 1:
        raise InputError(f"dataset.num_images must be >= 1; got {cfg.dataset.num_images}.")
    instantiate(cfg.dataset.source)  # NYU / RGB-D folder readers check their files in the constructor
