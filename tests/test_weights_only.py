"""Every weights file the project reads is unpickled as tensors only (torch.load without
weights_only runs arbitrary pickled code on torch < 2.6)."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LOADERS = {"torch.load", "torch.hub.load_state_dict_from_url", "load_state_dict_from_url"}


def loader_calls(tree: ast.AST):
    """(line, name, whether weights_only=True is passed) of every torch loader call, ``from torch
    import load`` included."""
    aliases = {
        alias.asname or alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("torch")
        for alias in node.names
        if alias.name == "load"
    }
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and ast.unparse(node.func) in LOADERS | aliases:
            safe = any(
                k.arg == "weights_only"
                and isinstance(k.value, ast.Constant)
                and k.value.value is True
                for k in node.keywords
            )
            yield node.lineno, ast.unparse(node.func), safe


def test_every_torch_load_of_the_project_is_weights_only():
    files = [
        p
        for folder in ("colmap_guided", "recon_scripts", "tests")
        for p in sorted((ROOT / folder).rglob("*.py"))
    ]
    calls = [
        (f.relative_to(ROOT), *call)
        for f in files
        for call in loader_calls(ast.parse(f.read_text(), str(f)))
    ]
    unsafe = [f"{f}:{line} {name}" for f, line, name, safe in calls if not safe]
    assert len(calls) >= 6 and not unsafe, f"torch loads without weights_only=True: {unsafe}"


def test_the_scan_sees_unsafe_loads():
    unsafe = (
        "import torch\nfrom torch import load as L\n"
        "torch.load(p)\ntorch.load(p, weights_only=False)\nL(p)\n"
    )
    safe = "import torch\ntorch.load(p, map_location='cpu', weights_only=True)\n"
    assert [s for *_, s in loader_calls(ast.parse(unsafe))] == [False, False, False]
    assert [s for *_, s in loader_calls(ast.parse(safe))] == [True]
