"""The service's modules import only downwards: no cycle, not even through an import inside a
function, and each module imports on its own in a fresh interpreter.

A cycle hidden in a function-level import is still a cycle (a newcomer cannot tell the layers
apart, and the order of first use decides what works). Imports in an ``if __name__ ==
"__main__":`` block are left out: they run only when the file is the program, as a module of
its own (``__main__``), never as the imported one.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "service" / "recal"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _is_main_block(node: ast.AST) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__")


def _imported(module: str, node: ast.AST) -> set[str]:
    """The recal modules an import statement names (``from recal import x`` names recal.x
    when that is a module)."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name.startswith("recal")}
    if not isinstance(node, ast.ImportFrom) or node.level or not node.module:
        return set()
    if not (node.module == "recal" or node.module.startswith("recal.")):
        return set()
    found = set()
    for a in node.names:
        sub = f"{node.module}.{a.name}"
        found.add(sub if sub in MODULES else node.module)
    return found


def _walk(module: str, node: ast.AST, edges: dict[str, set[str]],
          inside: dict[str, list[str]], in_function: bool) -> None:
    for child in ast.iter_child_nodes(node):
        if _is_main_block(child):
            continue
        targets = _imported(module, child)
        edges[module] |= targets
        if in_function:
            inside[module].extend(sorted(targets))
        _walk(module, child, edges, inside, in_function or isinstance(
            child, ast.FunctionDef | ast.AsyncFunctionDef))


def import_graph() -> tuple[dict[str, set[str]], dict[str, list[str]]]:
    """Every recal module's recal imports (module level and inside functions), and the
    function-level ones alone."""
    edges: dict[str, set[str]] = {m: set() for m in MODULES}
    inside: dict[str, list[str]] = {m: [] for m in MODULES}
    for module, path in MODULES.items():
        _walk(module, ast.parse(path.read_text()), edges, inside, False)
        edges[module] = {t for t in edges[module] if t != module and t in MODULES}
    return edges, inside


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """A cycle of the graph as a list of modules, or None."""
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        path.append(m)
        for t in sorted(edges[m]):
            if state.get(t) == 1:
                return [*path[path.index(t):], t]
            if t not in state and (found := visit(t)) is not None:
                return found
        state[m] = 2
        path.pop()
        return None

    for m in sorted(edges):
        if m not in state and (found := visit(m)) is not None:
            return found
    return None


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


def test_recal_imports_form_no_cycle() -> None:
    edges, _ = import_graph()
    assert find_cycle(edges) is None


def test_nothing_imports_the_command_line() -> None:
    """cli parses every command line and imports what it runs; nothing imports it back."""
    edges, _ = import_graph()
    users = sorted(m for m, targets in edges.items() if "recal.cli" in targets)
    assert users == ["recal.__main__"], users


def test_the_core_imports_only_the_core_and_the_data_types() -> None:
    edges, _ = import_graph()
    allowed = {"recal.errors", "recal.samples"}
    outside = {m: sorted(t for t in targets if not t.startswith("recal.core")
                         and t not in allowed)
               for m, targets in edges.items() if m.startswith("recal.core")}
    assert {m: t for m, t in outside.items() if t} == {}


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m != "recal.__main__"))
def test_each_module_imports_alone(module: str) -> None:
    done = subprocess.run([sys.executable, "-c", f"import {module}"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr


# --- the layers ------------------------------------------------------------------------------
#: what each package of the service must not import (core: see the test above)
FORBIDDEN = {
    "recal.io": ("recal.node", "recal.daemon", "recal.commands", "recal.sim"),
    "recal.node": ("recal.daemon", "recal.commands", "recal.sim"),
    "recal.config": ("recal.node", "recal.daemon", "recal.commands", "recal.sim"),
    "recal.daemon": ("recal.commands", "recal.sim"),
}
#: the only modules of the service that may import the simulator (tests and benches may too)
SIM_USERS = ("recal.commands", "recal.cli", "recal.sim")


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def layer_violations(edges: dict[str, set[str]]) -> dict[str, list[str]]:
    """Each module's imports that go against FORBIDDEN or SIM_USERS."""
    found: dict[str, list[str]] = {}
    for m, targets in sorted(edges.items()):
        bad = {t for pkg, banned in FORBIDDEN.items() if _in(m, pkg)
               for t in targets if any(_in(t, b) for b in banned)}
        if not any(_in(m, user) for user in SIM_USERS):
            bad |= {t for t in targets if _in(t, "recal.sim")}
        if bad:
            found[m] = sorted(bad)
    return found


def test_the_layer_rule_finds_a_wrong_import() -> None:
    edges = {"recal.io.bus": {"recal.node.node", "recal.core.model"},
             "recal.node.node": {"recal.io.bus", "recal.sim.wearer"},
             "recal.commands.demo": {"recal.sim.wearer", "recal.daemon.gateway"},
             "recal.daemon.gateway": {"recal.node.node", "recal.config.settings"}}
    assert layer_violations(edges) == {"recal.io.bus": ["recal.node.node"],
                                       "recal.node.node": ["recal.sim.wearer"]}


def test_each_package_imports_only_the_layers_below_it() -> None:
    """core <- io, config <- node <- daemon and commands; the simulator only for the commands
    and the command line (and tests and benches, outside the package)."""
    edges, _ = import_graph()
    assert layer_violations(edges) == {}


# --- the sizes -------------------------------------------------------------------------------
MAX_MODULE_LINES = 600
MAX_CLASS_ATTRIBUTES = 20
MAX_ROOT_MODULES = 8


def _is_dataclass(cls: ast.ClassDef) -> bool:
    for d in cls.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


def _self_targets(node: ast.AST) -> set[str]:
    """Names ``x`` of every ``self.x = ...`` (plain, annotated or unpacked) under ``node``."""
    names: set[str] = set()
    for n in ast.walk(node):
        targets: list[ast.expr] = (n.targets if isinstance(n, ast.Assign)
                                   else [n.target] if isinstance(n, ast.AnnAssign) else [])
        for t in targets:
            for e in ast.walk(t):
                if (isinstance(e, ast.Attribute) and isinstance(e.value, ast.Name)
                        and e.value.id == "self"):
                    names.add(e.attr)
    return names


def class_attributes(cls: ast.ClassDef) -> set[str]:
    """A class's instance attributes: its dataclass fields (annotated names in the class body,
    ClassVar aside) and every name its own methods assign on ``self``."""
    attrs: set[str] = set()
    for item in cls.body:
        if (_is_dataclass(cls) and isinstance(item, ast.AnnAssign)
                and isinstance(item.target, ast.Name)
                and "ClassVar" not in ast.unparse(item.annotation)):
            attrs.add(item.target.id)
        if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
            attrs |= _self_targets(item)
    return attrs


def test_the_attribute_count_sees_fields_and_self() -> None:
    tree = ast.parse("@dataclass(frozen=True)\nclass A:\n    x: int\n    y: ClassVar[int] = 1\n"
                     "    def f(self):\n        self.z, self.w = 1, 2\n        self.x: int = 3\n"
                     "class B:\n    n: int\n    def __init__(self):\n        self.a = 1\n")
    a, b = (n for n in tree.body if isinstance(n, ast.ClassDef))
    assert class_attributes(a) == {"x", "z", "w"} and class_attributes(b) == {"a"}


def test_no_module_is_too_long() -> None:
    long = {m: n for m, p in MODULES.items()
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_class_has_too_many_attributes() -> None:
    big = {}
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.ClassDef)
                    and (n := len(class_attributes(node))) > MAX_CLASS_ATTRIBUTES):
                big[f"{module}.{node.name}"] = n
    assert not big, f"classes over {MAX_CLASS_ATTRIBUTES} attributes: {big}"


def test_the_package_root_holds_few_modules() -> None:
    root = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(root) <= MAX_ROOT_MODULES, root
