"""The viewer in a real browser (headless Chromium through selenium): the page loads, a rendered frame
arrives and changes when the camera is dragged, and an edit made with the page's controls (select in
the region, move by a typed offset, apply, save) writes the same PLY as the pure edit functions."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest

pytest.importorskip("viser")
webdriver = pytest.importorskip("selenium.webdriver")

from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.common.keys import Keys  # noqa: E402

from ne_jax.data.ply import read_ply  # noqa: E402
from ne_jax.view import edits as E  # noqa: E402
from ne_jax.view.viewer import Viewer  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")

pytestmark = [pytest.mark.browser,
              pytest.mark.skipif(CHROMIUM is None or DRIVER is None,
                                 reason="needs chromium and chromedriver (Debian: apt-get install chromium "
                                        "chromium-driver)")]


def _wait(cond, what: str, timeout: float = 240.0):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if cond():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


@pytest.fixture
def browser():
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1000,700",
              "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
        opts.add_argument(a)
    driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
    yield driver
    driver.quit()


def _set_input(driver, label: str, value: str) -> None:
    """Type ``value`` into the (first) input of the GUI row labelled ``label``."""
    box = driver.find_element(By.XPATH, f"//label[normalize-space()='{label}']/ancestor::div[2]//input")
    box.click()
    box.send_keys(Keys.CONTROL, "a")
    box.send_keys(Keys.DELETE)
    box.send_keys(value)
    box.send_keys(Keys.TAB)


def _click(driver, text: str) -> None:
    driver.find_element(By.XPATH, f"//button[normalize-space()='{text}']").click()


def test_page_renders_moves_and_saves_an_edit(browser, tiny_run, tmp_path):
    viewer = Viewer(tiny_run, port=0, max_side=32, preview_factor=2, settle_s=0.3)
    try:
        browser.get(viewer.url)
        _wait(lambda: viewer.frames >= 1 and "full" in viewer._gui_time.content, "a full-resolution frame")
        first, n = viewer.last_frame.copy(), viewer.frames
        assert first.std() > 0
        canvas = browser.find_element(By.TAG_NAME, "canvas")
        ActionChains(browser).move_to_element_with_offset(canvas, -150, 0).click_and_hold() \
            .move_by_offset(120, 30).move_by_offset(60, 10).release().perform()
        _wait(lambda: viewer.frames > n and "full" in viewer._gui_time.content
              and not np.array_equal(viewer.last_frame, first), "a new frame after dragging the camera")

        _click(browser, "Select in region")
        _wait(lambda: viewer.selection.size > 0, "a selection")
        _set_input(browser, "Move by", "0.05")
        _wait(lambda: float(viewer._gui_move.value[0]) == 0.05, "the typed offset")
        _click(browser, "Apply move")
        _wait(lambda: len(viewer._history) == 1, "the move")
        out = tmp_path / "edited"
        _set_input(browser, "Save to", str(out))
        _wait(lambda: viewer._gui_out.value == str(out), "the typed folder")
        _click(browser, "Save")
        _wait(lambda: (out / E.EDIT_PLY).is_file(), "the saved edit")
    finally:
        viewer.stop()
    # the same edit through the pure functions: the default box region at the cloud's centre, moved by 0.05 in x
    pts = viewer.model.state.point_state(viewer.model.scene.points)
    edit = E.ViewEdit.identity(pts)
    xyz = edit.xyz[edit.remaining].astype(np.float64)
    center, extent = 0.5 * (xyz.min(0) + xyz.max(0)), float(np.linalg.norm(xyz.max(0) - xyz.min(0)))
    sel = E.select_region(edit, E.Region.make("box", center, round(0.3 * extent, 4)))
    np.testing.assert_array_equal(sel, viewer.selection)
    want = E.move_points(edit, sel, E.Transform.from_euler(E.selection_center(edit, sel), (0.05, 0.0, 0.0)))
    E.write_edit_ply(tmp_path / "want.ply", want)
    got, expected = read_ply(out / E.EDIT_PLY), read_ply(tmp_path / "want.ply")
    assert sorted(got) == sorted(expected)
    for k in expected:
        np.testing.assert_array_equal(got[k], expected[k])
