"""The package's layers import only downwards (docs/design.md, "Layout"), function-level imports included."""

from __future__ import annotations

import ast

from conftest import ROOT

# One rank per top-level unit of `ruslam`; a module may import its own unit or a lower rank only.
LAYERS = {
    "errors": 0, "atomic_files": 0,
    "cli": 1,
    "data": 2,
    "models": 3,
    "training": 4, "slam": 4, "features": 4,
    "config_checks": 5,
    "eval": 6,
    "train": 7, "evaluate": 7,
}


def _unit(module: str) -> str:
    return module.split(".")[1]


def test_no_module_imports_a_layer_above_its_own():
    upward = []
    for path in sorted((ROOT / "ruslam").rglob("*.py")):
        rel = path.relative_to(ROOT).with_suffix("")
        if rel.parts == ("ruslam", "__init__"):
            continue  # the package root re-exports load_extractor
        unit = rel.parts[1]
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
            for name in names:
                if name.startswith("ruslam.") and _unit(name) != unit and LAYERS[_unit(name)] >= LAYERS[unit]:
                    upward.append(f"{'/'.join(rel.parts)}.py:{node.lineno} imports {name}")
    assert upward == []
