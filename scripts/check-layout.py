#!/usr/bin/env python3
"""Checks two rules of the source layout (docs: README "Layout"; run by .ci/run):

1. no import cycle between the top-level modules of src/ in non-test code: an edge X -> Y for
   every `crate::Y` path (also inside `crate::{...}` groups) in a file of module X, comments
   and string literals excluded, each file cut at its first `#[cfg(test)]`; test-only files
   (`tests.rs`, `*_tests.rs`) left out;
2. no non-test source file over 1000 lines (files over 800 are listed as a warning).

Exit status 1 when a rule fails. `--graph` prints the module graph as well.
"""
import re
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parent.parent / "src"
HARD, SOFT = 1000, 800


def top_module(path: Path) -> str:
    rel = path.relative_to(SRC)
    if len(rel.parts) == 1:
        return rel.stem  # src/x.rs (lib.rs and main.rs are roots)
    return rel.parts[0]


def strip(text: str) -> str:
    """Non-test part of a file without comments and string literals."""
    cut = text.find("#[cfg(test)]")
    if cut >= 0:
        text = text[:cut]
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)
    text = re.sub(r"//[^\n]*", " ", text)
    text = re.sub(r'r#*"(?:.|\n)*?"#*', '""', text)
    text = re.sub(r'"(?:\\.|[^"\\])*"', '""', text)
    return text


def group_heads(body: str) -> list:
    """Top-level identifiers of a `{...}` use group (nested groups skipped)."""
    heads, depth, cur = [], 0, ""
    for ch in body:
        if ch == "{":
            depth += 1
        elif ch == "}":
            depth -= 1
        elif ch == "," and depth == 0:
            heads.append(cur)
            cur = ""
            continue
        if depth == 0:
            cur += ch
    heads.append(cur)
    out = []
    for h in heads:
        m = re.match(r"\s*(\w+)", h)
        if m and m.group(1) != "self":
            out.append(m.group(1))
    return out


def deps(text: str) -> set:
    found = set(re.findall(r"\bcrate::(\w+)", text))
    for m in re.finditer(r"\bcrate::\{", text):
        i, depth = m.end(), 1
        while i < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[i], 0)
            i += 1
        found.update(group_heads(text[m.end() : i - 1]))
    return found


def cycles(graph: dict) -> list:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def main() -> int:
    graph, sizes = {}, []
    modules = {top_module(p) for p in SRC.rglob("*.rs")}
    # Modules of the binary crate (declared in main.rs): their `crate::` paths are the binary's.
    binary = set(re.findall(r"^mod (\w+);", (SRC / "main.rs").read_text(), flags=re.M))
    for p in sorted(SRC.rglob("*.rs")):
        if p.name == "tests.rs" or p.name.endswith("_tests.rs"):
            continue
        raw = p.read_text()
        cut = raw.find("#[cfg(test)]")
        lines = (raw if cut < 0 else raw[:cut]).count("\n")
        sizes.append((lines, p.relative_to(SRC.parent)))
        m = top_module(p)
        if m in ("lib", "main") or m in binary:
            continue
        for d in deps(strip(raw)):
            if d in modules and d != m and d not in ("lib", "main"):
                graph.setdefault(m, set()).add(d)
        graph.setdefault(m, set())
    bad = False
    found = cycles(graph)
    if "--graph" in sys.argv:
        for m in sorted(graph):
            print(f"{m} -> {', '.join(sorted(graph[m]))}")
    if found:
        bad = True
        for c in found:
            print(f"import cycle between top-level modules: {' <-> '.join(c)}")
    else:
        print(
            f"import cycles between the {len(graph)} top-level modules of the library: none"
            f" (binary crate's modules: {', '.join(sorted(binary))})"
        )
    sizes.sort(reverse=True)
    over = [(n, p) for n, p in sizes if n > HARD]
    warn = [(n, p) for n, p in sizes if SOFT < n <= HARD]
    for n, p in over:
        print(f"over {HARD} lines of non-test code: {p} ({n})")
    for n, p in warn:
        print(f"warning: over {SOFT} lines of non-test code: {p} ({n})")
    print(f"largest non-test file: {sizes[0][1]} ({sizes[0][0]} lines)")
    bad |= bool(over)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
