"""The test suite's own layout (tests/README.md): a test module never imports another test module
(conftest included: what two modules share lives in tests/support), and the quick layers,
tests/core and tests/plugins, start no process (a test that runs a console script or a
subprocess belongs in tests/e2e, whose tests are all marked `slow`)."""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
#: Module names of the test tree that no module may import: every module outside tests/support.
TEST_MODULES = {p.stem for p in TESTS.rglob("*.py") if "support" not in p.relative_to(TESTS).parts}
#: What starts a process: these modules, and the helpers of support.commands that run `slamkit`.
PROCESS_MODULES = {"subprocess", "multiprocessing"}
PROCESS_HELPERS = {"run_slamkit", "Slamkit"}


def imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, names) of every import in the file, nested ones included; a relative
    import's module starts with its dots."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            found.append((node.lineno, "." * node.level + (node.module or ""), [a.name for a in node.names]))
    return found


def test_no_test_module_imports_another():
    offending = [f"{path.relative_to(TESTS)}:{line}: imports {module}"
                 for path in sorted(TESTS.rglob("*.py"))
                 for line, module, _ in imports(path)
                 if module.startswith(".") or module.split(".")[0] in TEST_MODULES]
    assert not offending, "move what they share into tests/support:\n" + "\n".join(offending)


def test_the_quick_layers_start_no_process():
    offending = [f"{path.relative_to(TESTS)}:{line}: imports {', '.join(names) or module}"
                 for layer in ("core", "plugins")
                 for path in sorted((TESTS / layer).glob("test_*.py"))
                 for line, module, names in imports(path)
                 if module.split(".")[0] in PROCESS_MODULES
                 or (module == "support.commands" and PROCESS_HELPERS & set(names))]
    assert not offending, "a test that starts a process belongs in tests/e2e:\n" + "\n".join(offending)


def test_every_module_lies_in_a_layer():
    loose = sorted(p.name for p in TESTS.glob("test_*.py"))
    assert not loose, f"test modules outside tests/core, tests/plugins and tests/e2e: {loose}"
