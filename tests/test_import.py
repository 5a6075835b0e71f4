"""``import torchrl_silp`` registers nothing with torch: no operator of its own, no torch.library call."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

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
