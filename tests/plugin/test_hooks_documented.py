"""Every hookspec has a docstring, a section in docs/hooks.md with its signature, and a test."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest
from helpers import REPO

from pstoolkit.plugin import spec as hookspecs

ROOT = REPO
DOCS = (ROOT / "docs" / "hooks.md").read_text()
HOOKS = sorted(name for name, obj in vars(hookspecs).items() if inspect.isfunction(obj) and hasattr(obj, "pstoolkit_spec"))


def test_the_hooks_are_found() -> None:
    assert len(HOOKS) == 11 and "pstoolkit_register_solvers" in HOOKS and "pstoolkit_add_commands" in HOOKS


@pytest.mark.parametrize("hook", HOOKS)
def test_hook_has_a_docstring(hook: str) -> None:
    assert (inspect.getdoc(getattr(hookspecs, hook)) or "").strip()


@pytest.mark.parametrize("hook", HOOKS)
def test_hook_has_a_docs_section_with_its_signature(hook: str) -> None:
    params = ", ".join(inspect.signature(getattr(hookspecs, hook)).parameters)
    assert f"\n## {hook}({params})\n" in DOCS


def test_docs_describe_no_other_hooks() -> None:
    assert sorted(re.findall(r"^## (\w+)\(", DOCS, flags=re.MULTILINE)) == HOOKS


@pytest.mark.parametrize("hook", HOOKS)
def test_hook_is_named_in_another_test_file(hook: str) -> None:
    others = [p for p in (ROOT / "tests").rglob("test_*.py") if p.name != Path(__file__).name]
    assert any(hook in p.read_text() for p in others), f"no test file mentions {hook}"
