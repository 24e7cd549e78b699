"""Kernels take their state as one structure (STYLE.md lesson 17): no numba-compiled function in
the product or the lab takes more than eight positional arguments. Read from the source with
`ast`, so nothing is compiled here."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_ARGUMENTS = 8


def _kernels(path: Path):
    """(name, line, number of arguments) of every function decorated with numba's jit."""
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not isinstance(node, ast.FunctionDef):
            continue
        if any("jit" in ast.unparse(d) for d in node.decorator_list):
            a = node.args
            yield node.name, node.lineno, len(a.posonlyargs) + len(a.args)


def test_no_kernel_takes_more_than_eight_arguments():
    files = [p for d in ("common", "services", "deploy", "lab") for p in (ROOT / d).rglob("*.py")]
    found = {}
    wide = []
    for path in files:
        for name, line, n in _kernels(path):
            found[name] = n
            if n > MAX_ARGUMENTS:
                wide.append(f"{path.relative_to(ROOT)}:{line} {name} takes {n}")
    # the scan really sees the kernels (a decorator spelled differently would hide them all)
    assert {"integrate_kernel", "_search", "label_pixels_kernel", "_tsdf_rows"} <= found.keys()
    assert not wide, "\n".join(wide)


def test_the_scan_would_catch_a_wide_kernel(tmp_path):
    wide = tmp_path / "wide.py"
    wide.write_text("@numba.njit(cache=True)\ndef _k(a, b, c, d, e, f, g, h, i):\n    pass\n")
    assert list(_kernels(wide)) == [("_k", 2, 9)]
