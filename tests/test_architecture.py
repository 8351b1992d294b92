"""The structure of the code: dependencies point one way (command line -> application ->
sim/hw), no module imports another's private names, no import cycles, and every
subcommand says what it does and what each option means.

The import graph is read from the source (every import statement, also those inside
functions), so the checks hold for what could be imported, not only for what one run did.
"""
from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("sim", "hw", "combined_reality")


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _resolve(module: str, is_package: bool, level: int, target: str | None) -> str:
    if level == 0:
        return target or ""
    base = module.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([target] if target else []))


class ImportGraph:
    """Modules of the project and what each imports: edges to modules, and names taken."""

    def __init__(self, root: Path, packages=PACKAGES, extra_dirs=()):
        self.files = {module_name(p, root): p for pkg in packages for p in (root / pkg).rglob("*.py")}
        self.edges: dict[str, set[str]] = {m: set() for m in self.files}
        self.private: list[tuple[str, str, str]] = []  # (importer, module, name)
        scripts = {f"{d}/{p.name}": p for d in extra_dirs for p in (root / d).glob("*.py")}
        for mod, path in [*self.files.items(), *scripts.items()]:
            self._read(mod, path, packages)

    def _add(self, mod: str, target: str) -> None:
        if target in self.files:
            self.edges.setdefault(mod, set()).add(target)

    def _read(self, mod: str, path: Path, packages) -> None:
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        is_package = path.name == "__init__.py"
        aliases: dict[str, str] = {}  # local name -> project module it is bound to
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                target = _resolve(mod, is_package, node.level, node.module)
                if target.split(".")[0] not in packages:
                    continue
                for a in node.names:
                    full = f"{target}.{a.name}"
                    if full in self.files:  # `from pkg import module`
                        self._add(mod, full)
                        aliases[a.asname or a.name] = full
                        continue
                    self._add(mod, target)
                    if a.name.startswith("_") and target != mod:
                        self.private.append((mod, target, a.name))
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] in packages:
                        self._add(mod, a.name)
                        if a.asname:
                            aliases[a.asname] = a.name
        for node in ast.walk(tree):  # module._private
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                    and isinstance(node.value, ast.Name) and node.value.id in aliases
                    and aliases[node.value.id] != mod):
                self.private.append((mod, aliases[node.value.id], node.attr))

    def cycles(self, group=lambda m: m) -> list[list[str]]:
        """Strongly connected components with more than one member, of the graph whose nodes
        are group(module) (the modules themselves, or their packages)."""
        g: dict[str, set[str]] = {}
        for a, targets in self.edges.items():
            if a not in self.files:
                continue
            ga = group(a)
            g.setdefault(ga, set())
            for b in targets:
                gb = group(b)
                if gb != ga:
                    g[ga].add(gb)
                    g.setdefault(gb, set())
        index, low, stack, on, out = {}, {}, [], set(), []
        counter = [0]

        def visit(v):
            index[v] = low[v] = counter[0]
            counter[0] += 1
            stack.append(v)
            on.add(v)
            for w in g[v]:
                if w not in index:
                    visit(w)
                    low[v] = min(low[v], low[w])
                elif w in on:
                    low[v] = min(low[v], index[w])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))

        for v in sorted(g):
            if v not in index:
                visit(v)
        return out


@pytest.fixture(scope="module")
def graph() -> ImportGraph:
    return ImportGraph(ROOT, extra_dirs=("benchmarks",))


def _layer(module: str) -> int:
    """sim 0, hw 1, the application 2, the command line 3: imports may only point down."""
    if module.startswith("sim"):
        return 0
    if module.startswith("hw"):
        return 1
    if module == "combined_reality.__main__" or module.startswith("combined_reality.cli"):
        return 3
    return 2


def test_dependencies_point_from_the_command_line_to_the_application_to_sim_and_hw(graph):
    upward = sorted(f"{a} imports {b}" for a, bs in graph.edges.items() if a in graph.files
                    for b in bs if _layer(b) > _layer(a))
    assert not upward, "imports against the layers (cli -> application -> hw -> sim):\n" + "\n".join(upward)


def test_no_module_imports_a_private_name_of_another(graph):
    found = sorted(f"{a} takes {name} from {b}" for a, b, name in graph.private)
    assert not found, ("private names used across modules (make them public where they belong):\n"
                       + "\n".join(found))


def test_no_import_cycles_between_modules(graph):
    assert graph.cycles() == []


def test_no_import_cycles_between_the_application_subpackages(graph):
    def package(m: str) -> str:
        parts = m.split(".")
        return ".".join(parts[:2]) if parts[0] == "combined_reality" and len(parts) > 1 else parts[0]

    assert graph.cycles(package) == []


def test_the_checks_find_what_they_look_for(tmp_path):
    """A small project with an upward import, a private import, a module._private access and
    a cycle: every check must see each of them (a check that cannot fail is no check)."""
    app = tmp_path / "combined_reality"
    (app / "cli").mkdir(parents=True)
    (tmp_path / "sim").mkdir()
    (tmp_path / "hw").mkdir()
    for d in (app, app / "cli", tmp_path / "sim", tmp_path / "hw"):
        (d / "__init__.py").write_text("")
    (app / "a.py").write_text("from .cli import common\nfrom .b import _helper\n")
    (app / "b.py").write_text("from . import a\n_helper = 1\n")
    (app / "c.py").write_text("from . import b\nx = b._helper\n")
    (app / "cli" / "common.py").write_text("")
    g = ImportGraph(tmp_path)
    assert [m for m in g.edges["combined_reality.a"] if _layer(m) > _layer("combined_reality.a")] \
        == ["combined_reality.cli.common"]
    assert sorted(g.private) == [("combined_reality.a", "combined_reality.b", "_helper"),
                                 ("combined_reality.c", "combined_reality.b", "_helper")]
    assert g.cycles() == [["combined_reality.a", "combined_reality.b"]]


def _subcommands():
    from combined_reality.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sorted(sub.choices.items())


@pytest.mark.parametrize("name", [n for n, _ in _subcommands()])
def test_every_subcommand_says_what_it_does_and_what_each_option_means(name):
    parser = dict(_subcommands())[name]
    assert parser.description and len(parser.description) > 40, f"{name} --help has no description"
    silent = [a.option_strings[0] if a.option_strings else a.dest for a in parser._actions
              if not isinstance(a, argparse._HelpAction) and not a.help]
    assert not silent, f"{name} --help does not explain: {', '.join(silent)}"


# what `--help` may load of the project: the command line, its option rules and the plain-data
# catalogues it states (the programs, the friction fits and segment defaults)
HELP_MAY_LOAD = ("combined_reality", "combined_reality.cli", "combined_reality.options", "combined_reality.errors",
                 "combined_reality.live", "combined_reality.live.catalogue", "combined_reality.friction",
                 "combined_reality.friction.specs", "sim", "sim.cylinder", "sim.errors", "sim.inputs")
HEAVY = ("casadi", "numpy", "scipy", "rerun", "can", "serial", "matplotlib", "pyarrow", "pint")


def test_help_loads_neither_the_numerics_nor_the_application():
    """`combined-reality --help` and every subcommand's `--help` stay fast: subcommands import the
    application when they run. One process asks for every help in turn and lists what it loaded."""
    import json
    import subprocess
    import sys

    code = ("import json, sys\nfrom combined_reality.cli import build_parser, main\n"
            "import argparse\n"
            "sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))\n"
            "codes = [main(['--help'])] + [main([name, '--help']) for name in sub.choices]\n"
            "print(json.dumps({'codes': codes, 'modules': sorted(sys.modules), 'n': len(sub.choices)}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    doc = json.loads(out.stdout.strip().splitlines()[-1])
    assert doc["n"] >= 12 and set(doc["codes"]) == {0}
    heavy = [m for m in doc["modules"] if m.split(".")[0] in HEAVY]
    assert not heavy, f"--help imported {heavy[:5]}"
    project = [m for m in doc["modules"] if m.split(".")[0] in PACKAGES and not m.startswith("combined_reality.cli.")
               and m not in HELP_MAY_LOAD]
    assert not project, f"--help imported the application: {project}"
