"""Figures of the package's layout (issue 32): modules per folder, the largest module and
function, top-level public names, command-line lines, and ``Any`` in kernel signatures.

    .venv/bin/python benchmarks/house_figures.py [SRC_PACKAGE_DIR]

Reads the source as text (ast), so it measures any checkout: pass another tree's
``src/echoloc`` to compare.
"""

from __future__ import annotations

import ast
import sys
from collections import Counter
from pathlib import Path


def _kernel_any_parameters(tree: ast.Module) -> int:
    count = 0
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            arguments = [*node.args.args, *node.args.kwonlyargs]
            if node.args.vararg is not None:
                arguments.append(node.args.vararg)
            count += sum(
                1 for a in arguments if a.annotation is not None and "Any" in ast.unparse(a.annotation)
            )
    return count


def _stub_names(package: Path) -> int:
    stub = package / "__init__.pyi"
    for node in ast.parse(stub.read_text()).body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            return len(ast.literal_eval(node.value))
    return 0


def main() -> None:
    package = (
        Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "src" / "echoloc"
    )
    per_folder: Counter[str] = Counter()
    largest_module = (0, "")
    largest_function = (0, "")
    kernel_any = 0
    cli_lines = 0
    for path in sorted(package.rglob("*.py")):
        relative = path.relative_to(package)
        text = path.read_text()
        lines = len(text.splitlines())
        per_folder[str(relative.parent)] += 1
        largest_module = max(largest_module, (lines, str(relative)))
        tree = ast.parse(text)
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno is not None:
                size = node.end_lineno - node.lineno + 1
                largest_function = max(largest_function, (size, f"{relative}:{node.name}"))
        if path.name.endswith("_kernels.py"):
            kernel_any += _kernel_any_parameters(tree)
        if path.name.startswith("cli") or relative.parts[0] == "cli":
            cli_lines += lines
    folders = ", ".join(f"{folder} {n}" for folder, n in sorted(per_folder.items(), key=lambda kv: -kv[1]))
    print(f"modules per folder: {folders}")
    print(f"largest module: {largest_module[1]}, {largest_module[0]} lines")
    print(f"largest function: {largest_function[1]}, {largest_function[0]} lines")
    print(f"top-level public names: {_stub_names(package)}")
    print(f"command-line lines: {cli_lines}")
    print(f"Any-annotated parameters in kernels: {kernel_any}")


if __name__ == "__main__":
    main()
