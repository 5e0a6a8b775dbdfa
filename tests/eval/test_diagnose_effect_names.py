"""Knowledge about one effect lives on the effect, not in string tables of the decision: no
module of ``eval/diagnose/`` writes an effect's name as a string literal (docstrings and
comments aside); it refers to the name through the effect (``RangeOffsetMapEffect.name``,
``Effect.mimicked_by``) or a constant of ``tofhil.sim.effects``."""

from __future__ import annotations

import ast
from pathlib import Path

import tofhil.eval.diagnose as diagnose_pkg
from tofhil.sim.effects import EFFECTS, SHAPE_SEPARATION, separation


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def effect_name_literals(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    docs = _docstrings(tree)
    return [f"{path.name}:{node.lineno}: {node.value!r}" for node in ast.walk(tree)
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in EFFECTS
            and id(node) not in docs]


def test_no_effect_name_is_a_string_literal_in_eval_diagnose():
    modules = sorted(Path(diagnose_pkg.__file__).parent.glob("*.py"))
    assert len(modules) > 10
    found = [hit for m in modules for hit in effect_name_literals(m)]
    assert not found, "effect names written as strings in eval/diagnose (refer to them through the effect):\n" \
        + "\n".join(found)


def test_the_check_sees_a_literal(tmp_path):
    """The check itself: a table keyed by an effect's name is found, its docstring is not."""
    name = next(iter(EFFECTS))
    f = tmp_path / "m.py"
    f.write_text(f'"""About {name!r}."""\nTABLE = {{{name!r}: 1}}  # {name}\n')
    assert effect_name_literals(f) == [f"m.py:2: {name!r}"]


def test_every_separating_capture_is_data_a_program_can_act_on():
    """Each pair an effect declares, and the one-view shape, carries its capture as a kind and
    a setting or a change, with the words beside them; a pair is found from either side."""
    pairs = [(e, other) for e, eff in EFFECTS.items() for other in eff.mimicked_by]
    assert pairs
    for a, b in pairs:
        assert b in EFFECTS, (a, b)
        sep = separation(a, b)
        assert separation(b, a) is sep
        data = sep.to_json()
        assert data["kind"] in ("acquisition", "bench_change") and data["text"]
        assert data.get("setting" if data["kind"] == "acquisition" else "change")
    assert SHAPE_SEPARATION.to_json()["change"] == "camera_pose"
    shaped = [e for e, eff in EFFECTS.items() if eff.mimicked_by_shape]
    assert {"range_offset_map", "field_angle"} <= set(shaped)
