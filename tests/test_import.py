"""``import torchrl_silp`` registers nothing with torch (no operator of its own, no torch.library call), and its modules import in any order."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# Run in a fresh interpreter: wraps every registration entry point of torch.library before the package
# is imported, records each call made directly from a file under the package's directory, then lists the
# operators the dispatcher holds in the package's namespace.
PROBE = textwrap.dedent(
    """
    import functools, importlib, inspect, json, os, sys
    import torch, torch.library

    package, root = sys.argv[1], sys.argv[2]
    calls = []

    def recorded(name, fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            # the direct caller only: importing a dependency from the package puts the package's
            # frames below every registration the dependency makes, and those are not the package's
            caller = inspect.currentframe().f_back
            path = os.path.abspath(caller.f_code.co_filename)
            if path.startswith(root):
                calls.append(f"torch.library.{name} from {path}:{caller.f_lineno}")
            return fn(*args, **kwargs)
        return wrapper

    ENTRY_POINTS = ["custom_op", "define", "impl", "impl_abstract", "register_autocast", "register_autograd",
                    "register_fake", "register_kernel", "register_torch_dispatch", "register_vmap", "triton_op"]
    for name in ENTRY_POINTS:
        if hasattr(torch.library, name):
            setattr(torch.library, name, recorded(name, getattr(torch.library, name)))
    library_init = torch.library.Library.__init__
    torch.library.Library.__init__ = recorded("Library", library_init)

    importlib.import_module(package)
    # the operators the dispatcher knows, each "namespace::name": those of the package's namespaces
    ops = [op for op in torch._C._dispatch_get_all_op_names() if op.split("::")[0].startswith(package)]
    print(json.dumps({"calls": calls, "ops": ops}))
    """
)


def probe(package: str, root: str, path: str | None = None) -> dict:
    env = dict(os.environ)
    if path is not None:
        env["PYTHONPATH"] = os.pathsep.join([path, *filter(None, [env.get("PYTHONPATH")])])
    out = subprocess.run([sys.executable, "-c", PROBE, package, root], capture_output=True, text=True, timeout=600,
                         env=env)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_importing_torchrl_silp_registers_no_operator():
    import torchrl_silp

    root = os.path.dirname(os.path.abspath(torchrl_silp.__file__))
    assert probe("torchrl_silp", root) == {"calls": [], "ops": []}


RELU_OP = {
    "custom_op": (
        "@torch.library.custom_op('registers_an_op::relu', mutates_args=())\n"
        "def relu(x: torch.Tensor) -> torch.Tensor:\n"
        "    return torch.relu(x)\n"
    ),
    "library": "lib = torch.library.Library('registers_an_op', 'FRAGMENT')\nlib.define('relu(Tensor x) -> Tensor')\n",
}


@pytest.mark.parametrize("how", sorted(RELU_OP))
def test_the_probe_sees_a_package_that_registers_an_operator(tmp_path, how):
    # the same probe on a package that does register one, each way a module can: it must say so
    package = tmp_path / "registers_an_op"
    package.mkdir()
    (package / "__init__.py").write_text("import torch\nimport torch.library\n\n" + RELU_OP[how])
    found = probe("registers_an_op", str(package), path=str(tmp_path))
    assert found["calls"] and found["ops"] == ["registers_an_op::relu"]


def test_the_package_s_module_level_imports_form_no_cycle():
    """Each module's top-level ``import torchrl_silp...`` statements as edges (a name imported from a
    package counts as its submodule where one exists): the graph has no cycle, so any module imports on
    its own, in any order."""
    import ast

    root = Path(__file__).resolve().parents[1] / "torchrl_silp"
    modules = {}
    for path in root.rglob("*.py"):
        parts = list(path.relative_to(root.parent).with_suffix("").parts)
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path

    def module_of(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for name, path in modules.items():
        imported = set()
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Import):
                imported |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported |= {node.module, *(f"{node.module}.{alias.name}" for alias in node.names)}
        graph[name] = {m for m in map(module_of, (i for i in imported if i.startswith("torchrl_silp"))) if m and m != name}
    assert {"torchrl_silp.models.base", "torchrl_silp.transforms"} <= set(graph)
    assert "torchrl_silp.transforms" in graph["torchrl_silp.models.base"]  # the graph holds real edges

    done, path_stack = set(), []

    def visit(name):
        if name in path_stack:
            raise AssertionError("import cycle: " + " -> ".join(path_stack[path_stack.index(name):] + [name]))
        if name in done:
            return
        path_stack.append(name)
        for other in sorted(graph[name]):
            visit(other)
        path_stack.pop()
        done.add(name)

    for name in sorted(graph):
        visit(name)
