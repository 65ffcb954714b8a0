"""HTML building blocks of the report: escaping, inlined images, relative video links, the image check hook."""

import base64
import io

import numpy as np
from PIL import Image

from harness.report import html as H
from harness.report.figures import encode_png, run_colours


def test_text_is_escaped_and_raw_html_is_not():
    table = H.table(["task"], [["<script>x</script>"], [H.Raw("<b>bold</b>")]])
    assert "&lt;script&gt;" in table and "<script>" not in table and "<b>bold</b>" in table
    assert H.fmt(float("nan")) == "n/a" and H.fmt(0.123456) == "0.123"
    assert "n/a" in H.fmt_ci(float("nan"), 0.0, 1.0) and "[0.1, 0.3]" in H.fmt_ci(0.2, 0.1, 0.3)


def test_images_are_inlined_and_videos_linked_relatively():
    png = encode_png(np.zeros((4, 6, 3), np.uint8))
    figure = H.image(png, "alt", "caption")
    data = figure.split("base64,")[1].split("'")[0]
    assert Image.open(io.BytesIO(base64.b64decode(data))).size == (6, 4)
    video = H.video("../runs/my run/Lift/episode_0/rollout.mp4")
    assert "src='../runs/my%20run/Lift/episode_0/rollout.mp4'" in video and "preload='none'" in video


def test_page_is_one_document_with_the_image_check_and_no_external_resources():
    page = H.page("T <1>", H.section("Sec", "body", anchor="s"), "sub", [("s", "Sec")])
    assert page.startswith("<!DOCTYPE html>") and "T &lt;1&gt;" in page
    assert "data-images-ok" in page and "<style>" in page
    assert "http" not in page.replace("http-equiv", "")
    assert len(set(run_colours(10))) == 10
