"""The package's import graph, read from the source with ``ast`` (nothing is imported).

Rules checked:

1. No cycles among module-level imports. These run when a module is imported, so a cycle makes the
   result depend on which module is imported first (a half-initialised module, an ImportError on a
   name not yet defined).
2. No cycles among all imports, function-level ones included, either. Lazy imports inside functions
   are how the package skips optional dependencies (Warp, PyOpenCL, Mitsuba, Ray, tqdm, matplotlib) and
   keeps ``import place3d_kernels`` light; they do not fail at import time, but a cycle through them
   still means two modules each need the other, i.e. one concept split across both. None is needed
   today, so none is allowed; a future one must be argued here and listed in ``ALLOWED_LAZY_CYCLES``.
3. No ``from place3d_kernels.x import _name`` across modules, at any level: a name with a leading
   underscore is its module's own business. Private *modules* (``_toml``, ``conditions/_common``) are
   package-internal by design and may be imported inside the package, but only their public names.
4. Backends (``place3d_kernels.backends``) import nothing from the domain above them.
5. Two wings: the library (``place3d_kernels``) never imports the application (``place3d_app``: the
   commands, the server and its client, the executors, the scene prefetch), at any level; the
   application imports the library. Every package of the repository is walked, so a cycle between the
   two (the client and the command line once had one) is found too.

Edges go from the importing module to the module named (``from pkg import mod`` counts as an edge to
``pkg.mod`` when ``mod`` is a module). The implicit import of a module's parent packages is left out:
every submodule "imports" its package ``__init__``, and ``place3d_kernels/__init__`` re-exports from its
submodules, so counting it would make every module part of one cycle by construction.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = "place3d_kernels"
APP = "place3d_app"
PACKAGES = (PKG, APP)
REPO = Path(__file__).resolve().parents[1]
ROOT = REPO / PKG

#: (importer, imported) lazy edges whose cycles are accepted, each with its reason. Empty on purpose.
ALLOWED_LAZY_CYCLES: set[tuple[str, str]] = set()


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for p in sorted((REPO / pkg).rglob("*.py")):
            parts = list(p.relative_to(REPO).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = p
    return mods


def _ours(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in PACKAGES)


MODULES = _modules()


def _resolve(importer: str, node: ast.ImportFrom) -> str | None:
    if node.level == 0:
        return node.module
    is_pkg = MODULES[importer].name == "__init__.py"
    base = importer.split(".")
    base = base if is_pkg else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _imports():
    """(importer, target module, imported name or None, function-level?, line) for intra-package imports."""
    out = []
    for mod, path in MODULES.items():
        tree = ast.parse(path.read_text(), str(path))

        def visit(node, in_function):
            for child in ast.iter_child_nodes(node):
                lazy = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
                if isinstance(child, ast.Import):
                    for a in child.names:
                        if _ours(a.name):
                            out.append((mod, a.name, None, in_function, child.lineno))
                elif isinstance(child, ast.ImportFrom):
                    target = _resolve(mod, child)
                    if target and _ours(target):
                        for a in child.names:
                            sub = f"{target}.{a.name}"
                            if sub in MODULES:
                                out.append((mod, sub, None, in_function, child.lineno))
                            else:
                                out.append((mod, target, a.name, in_function, child.lineno))
                visit(child, lazy)

        visit(tree, False)
    return out


IMPORTS = _imports()


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each as a readable cycle."""
    index, low, stack, on, comps = {}, {}, [], set(), []
    counter = [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                strong(w)
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
            if len(comp) > 1 or v in edges.get(v, ()):
                comps.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            strong(v)
    return comps


def _graph(include_lazy: bool) -> dict[str, set[str]]:
    g: dict[str, set[str]] = {}
    for src, dst, _, lazy, _ in IMPORTS:
        if dst not in MODULES or dst == src or (lazy and not include_lazy):
            continue
        if lazy and (src, dst) in ALLOWED_LAZY_CYCLES:
            continue
        g.setdefault(src, set()).add(dst)
    return g


def _explain(comps, g) -> str:
    lines = []
    for comp in comps:
        members = set(comp)
        lines.append(" <-> ".join(comp))
        seen = set()
        for src, dst, _, lazy, line in sorted(IMPORTS, key=lambda r: (r[0], r[4], r[1])):
            if src in members and dst in members and dst in g.get(src, ()) and (src, dst, line) not in seen:
                seen.add((src, dst, line))
                lines.append(f"    {MODULES[src].relative_to(REPO)}:{line} imports {dst}"
                             + (" (inside a function)" if lazy else ""))
    return "\n".join(lines)


def test_the_walk_sees_the_package():
    assert f"{PKG}.spec" in MODULES and f"{PKG}.backends.base" in MODULES and f"{APP}.cli" in MODULES
    assert any(dst == f"{PKG}.grid" for _, dst, _, _, _ in IMPORTS)
    # a cycle planted in a synthetic graph is found, so an empty result means something
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_module_level_import_cycles():
    g = _graph(include_lazy=False)
    comps = _cycles(g)
    assert not comps, "module-level import cycles:\n" + _explain(comps, g)


def test_no_import_cycles_through_function_level_imports():
    g = _graph(include_lazy=True)
    comps = _cycles(g)
    assert not comps, "import cycles (function-level imports included):\n" + _explain(comps, g)


def test_no_private_names_imported_across_modules():
    bad = [f"{MODULES[src].relative_to(REPO)}:{line} imports {name} from {dst}"
           + (" (inside a function)" if lazy else "")
           for src, dst, name, lazy, line in IMPORTS
           if name is not None and name.startswith("_") and not name.startswith("__") and dst != src]
    assert not bad, "private names imported across modules:\n" + "\n".join(bad)


def test_backends_do_not_import_the_domain():
    backends = f"{PKG}.backends"
    bad = [f"{MODULES[src].relative_to(REPO)}:{line} imports {dst}"
           for src, dst, _, _, line in IMPORTS
           if (src == backends or src.startswith(backends + "."))
           and not (dst == backends or dst.startswith(backends + "."))]
    assert not bad, "backends importing the domain:\n" + "\n".join(bad)


def _wing_violations(imports) -> list[str]:
    return [f"{src}:{line} imports {dst}" + (" (inside a function)" if lazy else "")
            for src, dst, _, lazy, line in imports
            if (src == PKG or src.startswith(PKG + ".")) and (dst == APP or dst.startswith(APP + "."))]


def test_the_library_does_not_import_the_application():
    bad = _wing_violations(IMPORTS)
    assert not bad, "library modules importing the application:\n" + "\n".join(bad)


def test_the_wing_rule_sees_a_planted_import():
    planted = [("place3d_kernels.metrics", "place3d_app.cli", None, True, 7),
               ("place3d_app.cli", "place3d_kernels.metrics", None, False, 3)]
    assert _wing_violations(planted) == ["place3d_kernels.metrics:7 imports place3d_app.cli (inside a function)"]
