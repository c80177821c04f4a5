"""The import graph of ``xmetro_ros``, computed from the code, and the package layers its docstrings declare.

Every ``import`` / ``from ... import`` statement at any depth (inside functions and ``if TYPE_CHECKING:`` blocks
too: a circle of type-only imports is still a circle for a reader), relative imports resolved. ``from P import n``
is an edge to the module ``P.n`` when that module exists, else to ``P`` (a name defined in ``P``). The implicit
import of a module's parent packages is not an edge.

The layer order is written once, in one place: the line ``May import: a, b, c.`` of each package's ``__init__.py``
docstring (``nothing of xmetro_ros`` for none). The generated interfaces ``msg`` / ``srv`` / ``action`` are
packages that may be named there. The root ``xmetro_ros/__init__.py`` (the version) may be imported by anyone;
the few modules beside the packages are entry points: they may import any package and nothing imports them.

``python test/import_graph.py`` prints the layer diagram that docs/architecture.md carries (a test compares them).
"""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field
from pathlib import Path

GENERATED = ("msg", "srv", "action")
MAY_IMPORT = re.compile(r"^May import:\s*(.+?)\.?\s*$", re.M)


def import_statements(path: Path, module: str) -> list[tuple[int, str, list[str]]]:
    """(line, absolute module, imported names) of every import statement in ``path`` (the module ``module``), at
    any depth, relative imports resolved: ``import a.b`` gives (line, "a.b", []), ``from ..c import d, e`` gives
    (line, "<package of module minus one level>.c", ["d", "e"])."""
    base = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: list[tuple[int, str, list[str]]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base.split(".")
                parts = parts[: len(parts) - (node.level - 1)]
                mod = ".".join(parts + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod, [a.name for a in node.names]))
    return out


@dataclass
class Edge:
    """``src`` imports ``dst`` (dotted module names) at ``line`` of ``src``."""

    src: str
    dst: str
    line: int


@dataclass
class ImportGraph:
    """Modules of one top-level package and the imports between them (``external``: the rest, for other rules)."""

    root: Path  # the directory holding the package
    package: str
    modules: dict[str, Path] = field(default_factory=dict)
    edges: list[Edge] = field(default_factory=list)
    external: list[Edge] = field(default_factory=list)

    @classmethod
    def scan(cls, root: Path, package: str = "xmetro_ros") -> ImportGraph:
        """Parse every module of ``root/package`` except the generated interfaces."""
        g = cls(root=root, package=package)
        pkg_dir = root / package
        for p in sorted(pkg_dir.rglob("*.py")):
            rel = p.relative_to(pkg_dir).parts
            if rel[0] in GENERATED:
                continue
            g.modules[g._name(p)] = p
        for name, p in g.modules.items():
            g._parse(name, p)
        return g

    def _name(self, path: Path) -> str:
        parts = list(path.relative_to(self.root).with_suffix("").parts)
        return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)

    def _resolve(self, dotted: str) -> str | None:
        """The module a dotted name lives in (longest existing prefix; ``<package>.msg`` etc. for the generated
        interfaces), None outside the package."""
        parts = dotted.split(".")
        if parts[0] != self.package:
            return None
        if len(parts) > 1 and parts[1] in GENERATED:
            return ".".join(parts[:2])
        while dotted and dotted not in self.modules:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    def _parse(self, name: str, path: Path) -> None:
        for line, mod, names in import_statements(path, name):
            # `from P import n` is an edge to the module P.n when it exists, else to P (a name defined in P)
            targets = [mod] if not names else [
                f"{mod}.{n}" if f"{mod}.{n}" in self.modules or f"{mod}.{n}" in self._generated() else mod
                for n in names]
            for t in targets:
                dst = self._resolve(t)
                if dst is None:
                    self.external.append(Edge(name, t, line))
                elif dst != name:
                    self.edges.append(Edge(name, dst, line))

    def _generated(self) -> set[str]:
        return {f"{self.package}.{g}" for g in GENERATED}

    # -- circles -------------------------------------------------------------------------------------------------
    def cycles(self) -> list[list[str]]:
        """One import circle per strongly connected component of two or more modules, as a closed path."""
        adj: dict[str, list[str]] = {m: [] for m in self.modules}
        for e in self.edges:
            if e.dst in adj and e.dst not in adj[e.src]:
                adj[e.src].append(e.dst)
        index: dict[str, int] = {}
        low: dict[str, int] = {}
        stack: list[str] = []
        on: set[str] = set()
        comps: list[list[str]] = []
        counter = 0
        for start in adj:  # iterative Tarjan
            if start in index:
                continue
            work = [(start, 0)]
            while work:
                v, i = work.pop()
                if i == 0:
                    index[v] = low[v] = counter
                    counter += 1
                    stack.append(v)
                    on.add(v)
                recurse = False
                for j in range(i, len(adj[v])):
                    w = adj[v][j]
                    if w not in index:
                        work.append((v, j + 1))
                        work.append((w, 0))
                        recurse = True
                        break
                    if w in on:
                        low[v] = min(low[v], index[w])
                if recurse:
                    continue
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        comps.append(comp)
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
        return [self._circle(set(c), adj) for c in comps]

    @staticmethod
    def _circle(comp: set[str], adj: dict[str, list[str]]) -> list[str]:
        """A shortest closed path through the component's first module (breadth-first)."""
        start = min(comp)
        prev: dict[str, str] = {}
        frontier = [start]
        while frontier:
            nxt = []
            for v in frontier:
                for w in adj[v]:
                    if w == start:
                        path = [v]
                        while path[-1] != start:
                            path.append(prev[path[-1]])
                        return [*reversed(path), start]
                    if w in comp and w not in prev:
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        return [start, start]

    # -- packages and layers -------------------------------------------------------------------------------------
    def package_of(self, module: str) -> str:
        """``scan`` for ``xmetro_ros.scan.geometry``; the root package's own name for ``xmetro_ros``; the module's
        name for an entry-level module beside the packages (``xmetro_ros.parts_seen``)."""
        parts = module.split(".")
        return parts[1] if len(parts) > 1 else parts[0]

    def packages(self) -> list[str]:
        """The sub-packages (directories with an ``__init__.py``), generated interfaces excluded."""
        return sorted({m.split(".")[1] for m, p in self.modules.items()
                       if p.name == "__init__.py" and m.count(".") == 1})

    def entry_modules(self) -> list[str]:
        """Modules beside the packages, ``__init__.py`` excluded."""
        return sorted(m for m, p in self.modules.items() if m.count(".") == 1 and p.name != "__init__.py")

    def allowed(self) -> dict[str, set[str]]:
        """Package → the packages its docstring's ``May import:`` line names (KeyError-free: a package without
        the line maps to None in :meth:`declaration_errors`)."""
        out: dict[str, set[str]] = {}
        for pkg in self.packages():
            doc = ast.get_docstring(ast.parse(self.modules[f"{self.package}.{pkg}"].read_text())) or ""
            m = MAY_IMPORT.search(doc)
            if m is None:
                continue
            text = m.group(1).strip()
            out[pkg] = set() if text.startswith("nothing") else {s.strip() for s in text.split(",") if s.strip()}
        return out

    def declaration_errors(self) -> list[str]:
        """Packages without a ``May import:`` line, names that are not packages, a circle in the declarations."""
        allowed = self.allowed()
        known = set(self.packages()) | set(GENERATED)
        errs = [f"{p}: no 'May import:' line in its __init__.py docstring" for p in self.packages() if p not in allowed]
        errs += [f"{p}: may import unknown package {q!r}" for p, qs in allowed.items() for q in sorted(qs - known)]
        try:
            self.layers()
        except ValueError as e:
            errs.append(str(e))
        return errs

    def layers(self) -> list[list[str]]:
        """The packages by layer, lowest first: a package sits one above the highest it may import."""
        allowed = {p: qs & set(self.packages()) for p, qs in self.allowed().items()}
        level: dict[str, int] = {}
        remaining = dict(allowed)
        while remaining:
            ready = [p for p, qs in remaining.items() if qs <= set(level)]
            if not ready:
                raise ValueError(f"the declared layers form a circle among {sorted(remaining)}")
            for p in ready:
                level[p] = 1 + max((level[q] for q in allowed[p]), default=-1)
                del remaining[p]
        out: list[list[str]] = [[] for _ in range(max(level.values(), default=-1) + 1)]
        for p, lv in level.items():
            out[lv].append(p)
        return [sorted(x) for x in out]

    def layer_violations(self) -> list[str]:
        """Imports a package's docstring does not allow, and imports of the entry-level modules."""
        allowed = self.allowed()
        entries = set(self.entry_modules())
        bad = []
        for e in self.edges:
            src, dst = self.package_of(e.src), self.package_of(e.dst)
            where = f"{self._rel(e.src)}:{e.line} imports {e.dst}"
            if e.dst in entries:
                bad.append(f"{where} (an entry module: nothing imports it)")
            elif src == dst or e.src in entries or dst == self.package or src == self.package:
                continue
            elif dst not in allowed.get(src, set()):
                bad.append(f"{where} ({src} may import {', '.join(sorted(allowed.get(src, ()))) or 'nothing'})")
        return bad

    def _rel(self, module: str) -> str:
        return str(self.modules[module].relative_to(self.root / self.package))

    def diagram(self) -> str:
        """The layers as text, highest first, with what each package may import."""
        allowed = self.allowed()
        lines = []
        for i, layer in reversed(list(enumerate(self.layers()))):
            for p in layer:
                uses = ", ".join(q for q in sorted(allowed[p], key=lambda q: (self._level(q), q))) or "—"
                lines.append(f"{i}  {p + '/':<12} may import: {uses}")
        return "\n".join(lines)

    def _level(self, pkg: str) -> int:
        for i, layer in enumerate(self.layers()):
            if pkg in layer:
                return i
        return 99  # generated interfaces last


if __name__ == "__main__":
    print(ImportGraph.scan(Path(__file__).resolve().parents[1]).diagram())
