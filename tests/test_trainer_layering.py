"""The trainer's package (train/worldpack_train) by floors, as tests/layering.rs holds the
crates: each module imports only its own floor and those below, the imports form no
circle, none hides inside a function, and no function runs past 120 lines. Reads the
source with `ast`; nothing is imported."""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "train" / "worldpack_train"
FLOORS = {"metrics": 0, "core": 1, "io": 2, "stages": 3, "settings": 4, "budget": 4, "card": 4, "pipeline": 4, "__main__": 4}
LONGEST = 120


def modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if parts:
            yield ".".join(parts), path, ast.parse(path.read_text())


def floor(module: str) -> int:
    head = module.split(".")[0]
    assert head in FLOORS, f"{module}: on no floor; add it to FLOORS in {Path(__file__).name}"
    return FLOORS[head]


def imported(module: str, node: ast.ImportFrom) -> list[str]:
    """The package modules a relative `from ... import ...` names (absolute ones are outside the package)."""
    if node.level == 0:
        return [node.module.removeprefix("worldpack_train.")] if node.module and node.module.startswith("worldpack_train") else []
    base = module.split(".")[: -node.level] if "." in module or node.level > 1 else []
    if node.level == 1 and "." not in module:
        base = []
    prefix = ".".join(base + ([node.module] if node.module else []))
    return [prefix] if node.module else [f"{prefix}.{a.name}".strip(".") for a in node.names]


def graph():
    edges = {}
    for module, path, tree in modules():
        edges[module] = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                edges[module] |= set(imported(module, node))
    return edges


def test_each_module_imports_only_its_floor_and_below():
    wrong = [f"{m} (floor {floor(m)}) imports {t} (floor {floor(t)})" for m, ts in graph().items() for t in ts if floor(t) > floor(m)]
    assert not wrong, wrong


def test_the_imports_form_no_circle():
    edges = graph()
    state = {}

    def visit(m, trail):
        if state.get(m) == "open":
            raise AssertionError("import circle: " + " -> ".join(trail[trail.index(m):] + [m]))
        if state.get(m) != "done":
            state[m] = "open"
            for t in sorted(edges.get(m, ())):
                visit(t, trail + [m])
            state[m] = "done"

    for m in sorted(edges):
        visit(m, [])


def test_no_import_inside_a_function():
    hidden = [f"{m}:{n.lineno}" for m, _, tree in modules() for f in ast.walk(tree)
              if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert not hidden, f"imports inside functions (move them to the top of the module): {hidden}"


def test_no_function_runs_past_the_limit():
    long = [f"{m}.{f.name}: {f.end_lineno - f.lineno + 1} lines" for m, _, tree in modules() for f in ast.walk(tree)
            if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) and f.end_lineno - f.lineno + 1 > LONGEST]
    assert not long, f"functions over {LONGEST} lines: {long}"


def test_the_checker_sees_a_circle_and_an_upward_import():
    # The rules above would pass on an empty graph; this holds them to the package's real edges.
    edges = graph()
    assert "core.config" in edges["core.cdit"] and "io.checkpoints" in edges["stages.denoiser"]
    assert floor("stages.export") > floor("io.onnx_files") > floor("core.config") > floor("metrics")
