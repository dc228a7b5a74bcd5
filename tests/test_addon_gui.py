"""The add-on in a real Blender window (Debian's blender 3.4.1 under Xvfb): the modal scan runs
in chunks to the end, undo and redo take its clouds away and back, Esc cancels a running scan
and removes what it had made."""

from pathlib import Path

import pytest
from blender_window import run_in_window, virtual_display

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def display():
    with virtual_display("1280x800") as num:
        yield num


def test_modal_scan_undo_and_escape_in_a_window(tmp_path, display):
    rep = run_in_window(tmp_path, display, "addon_gui_script.py")
    assert rep["invoke"] == ["RUNNING_MODAL"] and rep["right_after_invoke"] == 0
    assert rep["after_modal_scan"] == 12
    assert rep["after_undo"] == 0 and rep["after_redo"] == 12
    assert rep["invoke_again"] == ["RUNNING_MODAL"]
    assert 2 <= rep["before_esc"] < 12 and rep["after_esc"] == 0
    assert rep["scenes_after_scan"] == rep["scenes_after_esc"] == 1  # nothing left behind
