"""The report as a browser shows it: `benchmark.browser_check` loads a page in headless Chromium (Debian's
`chromium`) and reports images that do not load and console errors. Skipped where no Chromium is installed;
the real report is checked in tests/test_benchmark_ci_eval.py."""
from __future__ import annotations

import numpy as np
import pytest

from benchmark.browser_check import check_page, find_browser
from lumibench.errors import UserError
from lumibench.io import read_image, write_png

pytestmark = pytest.mark.skipif(find_browser() is None, reason="no Chromium (Debian package `chromium`)")


def _page(tmp_path, body: str):
    img = np.zeros((40, 60, 3))
    img[..., 0] = 1.0  # a red picture: the screenshot must show it
    write_png(tmp_path / "red.png", img)
    (tmp_path / "page.html").write_text(f"<html><body style='margin:0'>{body}</body></html>")
    return tmp_path / "page.html"


def test_a_clean_page_passes_and_its_screenshot_shows_it(tmp_path):
    res = check_page(_page(tmp_path, "<img src='red.png' width=60 height=40><p>ok</p>"),
                     screenshot=tmp_path / "shot.png")
    assert res.ok and res.images == [("red.png", True)] and res.console_errors == []
    shot = read_image(tmp_path / "shot.png")
    assert shot.shape[0] >= 40 and shot.shape[1] >= 60
    top_left = shot[5:35, 5:55, :3]
    assert top_left[..., 0].min() > 0.9 and top_left[..., 1].max() < 0.1  # the image itself, not a placeholder


def test_broken_images_console_errors_and_exceptions_are_reported(tmp_path):
    res = check_page(_page(tmp_path, "<img src='red.png'><img src='charts/missing.png'>"
                                     "<script>console.error('chart', 7); undefinedFunction();</script>"))
    assert not res.ok
    assert res.broken_images == ["charts/missing.png"]
    errs = "\n".join(res.console_errors)
    assert "console.error: chart 7" in errs
    assert "undefinedFunction" in errs  # the uncaught ReferenceError
    assert "missing.png" in errs  # the failed load, from the network log


def test_a_missing_report_is_a_one_line_error(tmp_path):
    with pytest.raises(UserError, match="no such report"):
        check_page(tmp_path / "report.html")
