"""Exercises that check themselves (issue 89): each check fails on the untouched stub, passes on
the reference answer, and says what is off, with a hint, on a wrong one."""

from __future__ import annotations

from pathlib import Path

import pytest

from e2e_lite.exercises.checks import EXERCISES, STUBS, check, main

ANSWERS = Path(__file__).parent / "exercise_answers"


@pytest.mark.parametrize("number", sorted(EXERCISES))
def test_a_check_fails_on_its_stub_and_passes_on_the_reference_answer(number: str) -> None:
    ok, line = check(number, STUBS)
    assert not ok and "not answered yet" in line
    ok, line = check(number, ANSWERS)
    assert ok and line == f"{number}: pass", line


def test_a_wrong_answer_gets_what_is_off_and_a_hint(tmp_path: Path, capsys) -> None:
    (tmp_path / "ex_01_4.py").write_text("def miles():\n    return 300.0\n")
    ok, line = check("01.4", tmp_path)
    assert not ok and "rule of three" in line
    (tmp_path / "ex_01_4.py").write_text("def miles():\n    return 100.0\n")
    ok, line = check("01.4", tmp_path)
    assert not ok and "expected about 368.9" in line and "Hint" in line
    (tmp_path / "ex_07_3.py").write_text(
        "def mixture_mean(weights, modes):\n    return modes[:, 0]\n"
    )
    ok, line = check("07.3", tmp_path)
    assert not ok and "weighted mean" in line
    (tmp_path / "ex_03_2.py").write_text("def steady_error_m():\n    return 0.1\n")
    assert not check("03.2", tmp_path)[0]
    (tmp_path / "ex_01_1.py").write_text("def lookahead_m():\n    return 90.0\n")
    ok, line = check("01.1", tmp_path)
    assert not ok and "look-ahead [m]: 90" in line and "half widths" in line
    # the command: exit 1 on a failed check, 2 on an unknown exercise
    assert main(["check", "01.4", "--stubs", str(tmp_path)]) == 1
    assert main(["check", "99.9"]) == 2
    assert "99.9" in capsys.readouterr().err
