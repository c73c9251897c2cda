"""The package's folders are its layers: every import points down, and no module imports itself
back through others (docs/DESIGN.md section 2).

Independent of the import system: the imports are read from the source with ``ast`` (those
inside functions too, so that none can hide a cycle), resolved to files of the package, and
checked against the layer order written here.
"""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jaximu"

# Lowest first. A module may import modules of its own layer (without a cycle) and of the
# layers before it. ``errors`` is the one module of the lowest layer; the package root
# (``jaximu/__init__.py``, ``__main__.py`` and the modules that keep the old import paths,
# e.g. ``jaximu/so3.py``) is the facade above them all, and no layer imports it.
LAYERS = (
    "errors",
    "geometry",
    "schemes",
    "kernels",
    "engine",
    "io",
    "studies",
    "calibration",
    "learning",
    "app",
)


def module_names():
    """``{dotted name: path}`` of every module of the package."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = ("jaximu",) + path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


MODULES = module_names()


def imports_of(name, path):
    """The package's modules that ``name`` imports, anywhere in its source."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([base] if base else []))
            # a name imported from a package is a module when there is one of that name
            targets = [
                f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names
            ]
        else:
            continue
        for t in targets:
            while t and t not in MODULES and "." in t:  # `import jaximu.a.b` names a module
                t = t.rsplit(".", 1)[0]
            if t in MODULES and t != name:
                out.add(t)
    return out


GRAPH = {name: imports_of(name, path) for name, path in MODULES.items()}


def layer_of(name):
    """The layer of a module, or ``None`` for the facade at the package root."""
    parts = name.split(".")
    if len(parts) == 1 or parts[1] not in LAYERS:
        return None
    return parts[1]


def test_every_module_has_a_layer():
    facade = sorted(n for n in MODULES if layer_of(n) is None)
    # the facade is the package's own __init__, __main__, and thin modules of re-exports
    for name in facade:
        if name in ("jaximu", "jaximu.__main__"):
            continue
        tree = ast.parse(MODULES[name].read_text(encoding="utf-8"))
        defs = [
            n
            for n in tree.body
            if isinstance(n, (ast.FunctionDef, ast.ClassDef)) and n.name != "__getattr__"
        ]  # a module's forwarding of its other names
        assert not defs, (
            f"{name} sits at the package root but defines {defs[0].name}: "
            f"give it a home in one of {LAYERS}"
        )


def test_imports_point_down():
    bad = []
    for name, targets in GRAPH.items():
        mine = layer_of(name)
        if mine is None:
            continue
        for t in sorted(targets):
            theirs = layer_of(t)
            if theirs is None:
                bad.append(f"{name} imports the facade module {t}")
            elif LAYERS.index(theirs) > LAYERS.index(mine):
                bad.append(f"{name} ({mine}) imports {t} ({theirs}), a higher layer")
    assert not bad, "\n".join(bad)


def strongly_connected(graph):
    """Tarjan's strongly connected components of ``graph`` (``{node: set of nodes}``)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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
            out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycle():
    cycles = [c for c in strongly_connected(GRAPH) if len(c) > 1]
    assert not cycles, f"import cycles: {cycles}"


def test_the_cycle_check_finds_a_planted_cycle():
    """The check itself: a cycle of three and a self-contained pair are found, a chain is not."""
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"e"}, "e": set(), "f": {"g"}, "g": {"f"}}
    assert sorted(c for c in strongly_connected(g) if len(c) > 1) == [["a", "b", "c"], ["f", "g"]]


def test_layers_are_folders():
    """Every layer but ``errors`` is a folder of the package, and every folder is a layer."""
    folders = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    assert folders == set(LAYERS) - {"errors"}
    assert (ROOT / "errors.py").is_file()
