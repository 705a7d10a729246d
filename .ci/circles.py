#!/usr/bin/env python3
"""Circles of files inside a crate: `python3 .ci/circles.py CRATE/src [...]`.

Each file is a module. File A depends on file B when A names something of B by a path
(`crate::b::..`, `super::..`, `self::..`, or a child's name in a mod.rs/lib.rs), in a `use`
or inline. A re-export (`pub use x::Y`) is an alias, not a use: a path through it is
followed to the file that defines the item. `mod x;` declares, it does not use. Tests at the
end of a file (from its `#[cfg(test)]` on) are left out: they may use anything.

A type's methods may be spread over several files' `impl T` blocks; a call `self.f(..)`
in one of them of a method defined in another file is a dependency no path shows, and is
counted as one.

Exit status 1, and each circle printed, when there is one."""
import os
import re
import sys

IDENT = r"[A-Za-z_][A-Za-z0-9_]*"


def modules(src):
    """Map module path (tuple) -> file, for every .rs file under src."""
    out = {}
    for root, _dirs, files in os.walk(src):
        for f in files:
            if not f.endswith(".rs"):
                continue
            rel = os.path.relpath(os.path.join(root, f), src)
            parts = rel[:-3].split(os.sep)
            if parts[-1] in ("mod", "lib", "main"):
                parts = parts[:-1]
                if f == "main.rs" and not parts:
                    continue  # the binary is its own crate
            out[tuple(parts)] = os.path.join(root, f)
    return out


def code_of(path):
    text = open(path, encoding="utf-8").read()
    cut = text.find("#[cfg(test)]")
    if cut >= 0:
        text = text[:cut]
    text = re.sub(r"//[^\n]*", "", text)
    return text


def expand_use(body):
    """`a::{b, c::{d, e}}` -> ['a::b', 'a::c::d', 'a::c::e'] (leaf names kept)."""
    body = re.sub(r"\s+", "", body)

    def split_top(s):
        depth, cur, parts = 0, "", []
        for ch in s:
            if ch == "{":
                depth += 1
            elif ch == "}":
                depth -= 1
            if ch == "," and depth == 0:
                parts.append(cur)
                cur = ""
            else:
                cur += ch
        if cur:
            parts.append(cur)
        return parts

    def go(s):
        i = s.find("{")
        if i < 0:
            return [re.sub(r"\bas\w+$", "", s)]
        head, inner = s[:i], s[i + 1 : s.rfind("}")]
        out = []
        for p in split_top(inner):
            for leaf in go(p):
                out.append(head + leaf)
        return out

    return go(body)


def main(srcs):
    failed = False
    for src in srcs:
        mods = modules(src)
        codes = {m: code_of(p) for m, p in mods.items()}
        # Re-exports: (module, name) -> absolute path segments of the target.
        reexports = {}
        uses = {}
        for m, code in codes.items():
            uses[m] = []
            for vis, body in re.findall(r"(?m)^\s*(pub(?:\([^)]*\))?\s+)?use\s+([^;]+);", code):
                for p in expand_use(body):
                    name = p.split("::")[-1]
                    if name not in ("*", "self"):
                        # Any `use` makes a name of the module that its children may
                        # reach through `super::`: followed to what it names.
                        reexports[(m, name)] = p
                    if not vis:
                        uses[m].append(p)

        def absolute(m, path):
            seg = path.split("::")
            if seg[0] == "crate":
                return list(seg[1:])
            if seg[0] in ("super", "self"):
                base = list(m)
                while seg and seg[0] in ("super", "self"):
                    if seg[0] == "super":
                        base = base[:-1]
                    seg = seg[1:]
                return base + seg
            if tuple(list(m) + [seg[0]]) in mods:
                return list(m) + seg
            return None  # an external crate or a local name

        def resolve(segs, depth=0):
            """The file (module path) that defines what segs names."""
            cur = ()
            for i, s in enumerate(segs):
                if tuple(list(cur) + [s]) in mods:
                    cur = tuple(list(cur) + [s])
                    continue
                target = reexports.get((cur, s))
                if target is not None and depth < 8:
                    t = absolute(cur, target)
                    if t is not None:
                        return resolve(t + segs[i + 1 :], depth + 1)
                break
            return cur

        edges = {m: set() for m in mods}
        for m, code in codes.items():
            paths = list(uses[m])
            stripped = re.sub(r"(?ms)^\s*(pub(?:\([^)]*\))?\s+)?use\s+[^;]+;", "", code)
            paths += re.findall(r"\b((?:crate|super|self)(?:::%s)+)" % IDENT, stripped)
            paths += re.findall(r"(?<![:\w])(%s(?:::%s)+)" % (IDENT, IDENT), stripped)
            for p in paths:
                a = absolute(m, p)
                if a is None:
                    continue
                t = resolve(a)
                if t != m and t in mods:
                    edges[m].add(t)
        # Types and where they are defined.
        defined = {}
        for m, code in codes.items():
            for t in re.findall(r"(?m)^\s*(?:pub(?:\([^)]*\))?\s+)?(?:struct|enum)\s+(%s)" % IDENT, code):
                defined.setdefault(t, set()).add(m)
        # A type's methods may be spread over files (`impl T` blocks away from T's home).
        # A call `self.f(..)` in one `impl T` of a method defined in another file's
        # `impl T` is a use of that file no path shows.
        methods = {}  # (type, method) -> files defining it
        bodies = []  # (file, type, block)
        for m, code in codes.items():
            for t, block in impl_blocks(code):
                bodies.append((m, t, block))
                for f in re.findall(r"\bfn\s+(%s)" % IDENT, block):
                    methods.setdefault((t, f), set()).add(m)
        for m, t, block in bodies:
            for f in set(re.findall(r"\bself\s*\.\s*(%s)\s*(?:::<[^>]*>)?\(" % IDENT, block)):
                for home in methods.get((t, f), ()):
                    if home != m:
                        edges[m].add(home)
        for cycle, comp in cycles(edges):
            failed = True
            names = [("/".join(c) or "lib") + ".rs" for c in cycle]
            print(f"circles: {src}: " + " -> ".join(names + [names[0]]))
            if len(comp) > len(cycle):
                files = ", ".join(("/".join(c) or "lib") + ".rs" for c in comp)
                print(f"  (one of the circles among {files})")
    return 1 if failed else 0


def impl_blocks(code):
    """(type, body) of each top-level impl block; `impl Trait for T` counts as T's."""
    pat = r"(?m)^impl(?:<[^>]*>)?\s+(?:%s(?:<[^{]*?>)?\s+for\s+)?(%s)(?:<[^{]*>)?\s*\{" % (IDENT, IDENT)
    for mt in re.finditer(pat, code):
        depth, i = 1, mt.end()
        while i < len(code) and depth:
            depth += {"{": 1, "}": -1}.get(code[i], 0)
            i += 1
        yield mt.group(1), code[mt.end() : i]


def cycles(edges):
    """One cycle per strongly connected component of more than one file (Tarjan)."""
    index, low, stack, on, out, n = {}, {}, [], set(), [], [0]

    def strong(v):
        index[v] = low[v] = n[0]
        n[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(edges[v]):
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
            if len(comp) > 1:
                out.append((one_cycle(edges, set(comp)), sorted(comp)))

    sys.setrecursionlimit(10000)
    for v in sorted(edges):
        if v not in index:
            strong(v)
    return out


def one_cycle(edges, comp):
    start = min(comp)
    prev, todo = {start: None}, [start]
    while todo:
        v = todo.pop(0)
        for w in sorted(edges[v]):
            if w == start:
                path = [v]
                while prev[path[-1]] is not None:
                    path.append(prev[path[-1]])
                return list(reversed(path))
            if w in comp and w not in prev:
                prev[w] = v
                todo.append(w)
    return sorted(comp)


def self_test():
    """The check judges: two small crates with a circle each (a path; a method call), and
    one without, in a temporary directory."""
    import contextlib
    import io
    import tempfile

    cases = {
        "by a path": ({"lib.rs": "mod a;\nmod b;\n", "a.rs": "use super::b::B;\npub struct A;\n",
                       "b.rs": "pub struct B;\nfn f() { let _ = super::a::A; }\n"}, 1),
        "by a method": ({"lib.rs": "mod w;\nmod h;\n",
                         "w.rs": "pub struct W;\nimpl W {\n    fn run(&self) { self.handle(); }\n}\n",
                         "h.rs": "use super::w::W;\nimpl W {\n    pub(super) fn handle(&self) {}\n}\n"}, 1),
        "none": ({"lib.rs": "mod w;\nmod h;\npub use w::W;\n",
                  "w.rs": "pub struct W;\nimpl W {\n    fn base(&self) {}\n}\n",
                  "h.rs": "use crate::W;\nimpl W {\n    pub(super) fn handle(&self) { self.base(); }\n}\n"}, 0),
    }
    bad = 0
    for name, (files, want) in cases.items():
        with tempfile.TemporaryDirectory() as d:
            for f, text in files.items():
                with open(os.path.join(d, f), "w", encoding="utf-8") as out:
                    out.write(text)
            with contextlib.redirect_stdout(io.StringIO()):
                got = main([d])
        if got != want:
            print(f"circles: self-test {name!r}: exit {got}, expected {want}")
            bad = 1
    return bad


if __name__ == "__main__":
    if sys.argv[1:] == ["--self-test"]:
        sys.exit(self_test())
    sys.exit(main(sys.argv[1:]))
