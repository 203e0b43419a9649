"""The web viewer (/viewer) in a real headless Chromium against a real
`worldpack serve`: driven through the page's own controls, checked by what
the page shows. Chromium comes from Debian (scripts/test.sh installs it)."""

import base64
import os
import shutil
import struct
import zlib
from pathlib import Path

import pytest
from playwright.sync_api import sync_playwright

from test_python_client import start
from worldpack_client import Client

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# Chromium's own background traffic is refused on a closed network; these flags keep it quiet.
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def browser():
    if not os.path.exists(CHROMIUM):
        pytest.fail(f"no Chromium at {CHROMIUM}: scripts/test.sh installs Debian's chromium package")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        yield b
        b.close()


def offline_page(browser, url):
    """A page that may only reach the server: any other request fails the test.
    (Images the page fetched itself show through object URLs of its own origin.)"""
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    foreign = []
    local = (url, "data:", f"blob:{url}")
    page.on("request", lambda r: None if r.url.startswith(local) else foreign.append(r.url))
    return page, foreign


def map_pixels(page):
    return page.eval_on_selector("#map", "c => c.toDataURL()")


def test_a_synthetic_session_driven_from_the_page(browser, tmp_path):
    # VIEWER_SERVE picks the server's flags (docs/viewer.md makes the README's picture with the main job's model).
    proc, url = start(tmp_path, *os.environ.get("VIEWER_SERVE", "--steps 2").split())
    try:
        page, foreign = offline_page(browser, url)
        page.goto(url + "/")  # redirects to /viewer
        assert page.url.endswith("/viewer")
        failed = []  # every answer of 400 or more the page gets
        page.on("response", lambda r: failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)
        page.wait_for_function("document.querySelector('#server').textContent.includes('model')")
        # Before any session: no broken images, an empty box that says why.
        assert page.get_attribute("#frame", "src") is None
        assert page.is_visible("#frame-empty") and page.is_visible("#truth-empty")
        page.fill("#seed", "3")
        page.click("#create")
        page.wait_for_function("document.querySelector('#session-label').textContent.includes('1 frame,')")
        # The first frame's truth is shown (the world renders it), and the empty boxes are gone.
        page.wait_for_function("!!document.querySelector('#truth').getAttribute('src')")
        assert not page.is_visible("#frame-empty") and not page.is_visible("#truth-empty")
        blank_map = map_pixels(page)
        # Keyboard and buttons: three steps forward, a turn, one more forward; the
        # keyboard drives right after a click on a checkbox (clicked twice: left off).
        for i, press in enumerate(["w", "w", "w", "button:ArrowRight", "checkbox", "w"], start=1):
            if press == "checkbox":
                page.click("#observe")
                page.click("#observe")
                page.keyboard.press("w")
            elif press.startswith("button:"):
                page.click(f"#drive button[data-key='{press.split(':')[1]}']")
            else:
                page.keyboard.press(press)
            page.wait_for_function(f"document.querySelector('#frame').dataset.index === '{i}'")
            # The status line follows the session.
            assert f"{i + 1} frames" in page.inner_text("#session-label"), page.inner_text("#session-label")
        assert page.get_attribute("#frame", "src").startswith("data:image/png;base64,")
        assert "PSNR" in page.inner_text("#metrics")
        thumbs = page.query_selector_all("#plan .thumb")
        assert len(thumbs) == 6, "WorldPack packs every earlier frame while there are fewer than 22"
        rates = [t.get_attribute("data-rate") for t in thumbs]
        assert rates == ["1", "1", "4", "4", "4", "4"], "best two at full rate, the next four at 1/4"
        assert page.get_attribute("#map", "data-frames") == "7"
        assert page.get_attribute("#map", "data-frusta") == "6"
        assert map_pixels(page) != blank_map
        assert len(page.query_selector_all("#strip img")) == 7
        # Every thumbnail loaded from the server.
        page.wait_for_function("[...document.querySelectorAll('#plan img')].every(i => i.complete && i.naturalWidth === 64)")
        assert "sample" in page.inner_text("#timings")
        # A server error is shown with the field it names.
        page.fill("#open-id", "999999")
        page.click("#open")
        page.wait_for_function("document.querySelector('#error').textContent.includes('session')")
        page.fill("#open-id", "1")
        page.click("#open")
        page.wait_for_function("document.querySelector('#error').textContent === ''")
        page.wait_for_function("document.querySelector('#session-label').textContent.includes('7 frames')")
        page.wait_for_function("!!document.querySelector('#truth').getAttribute('src')")
        # The only refusal the page met is the session that does not exist.
        assert [f for f in failed if "/v1/sessions/999999" not in f] == [], failed
        out = Path(os.environ.get("VIEWER_SCREENSHOT", tmp_path / "viewer.png"))
        out.parent.mkdir(parents=True, exist_ok=True)
        page.keyboard.press("w")
        page.wait_for_function("document.querySelector('#frame').dataset.index === '7'")
        page.wait_for_function("[...document.querySelectorAll('img')].every(i => !i.src || i.complete)")
        page.screenshot(path=str(out), full_page=True)
        assert out.stat().st_size > 10_000
        assert foreign == [], f"the page fetched from elsewhere: {foreign}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def png(width, height, shade):
    """A flat-coloured RGB PNG, written by hand (no image library needed)."""
    raw = b"".join(b"\x00" + bytes([shade, 255 - shade, 128]) * width for _ in range(height))
    chunk = lambda kind, data: struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)) + \
        chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def test_memory_only_mode_selects_where_the_map_is_clicked(browser, tmp_path):
    proc, url = start(tmp_path, "--memory-only")
    try:
        # A stored session of real frames: six views along +z, all facing +z.
        client = Client(url)
        facing_z = [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]
        frames = [{"image_png": base64.b64encode(png(64, 48, 40 * i)).decode(), "pose": {"c2w": {"rotation": facing_z, "position": [0, 0, 2.0 * i]}}}
                  for i in range(6)]
        created = client.request("POST", "/v1/sessions", {"frames": frames, "intrinsics": {"hfov_deg": 70, "width": 64, "height": 48}})
        page, foreign = offline_page(browser, url)
        page.goto(url + "/viewer")
        page.wait_for_function("document.querySelector('#server').textContent.includes('memory only')")
        assert page.is_hidden("#drive") and page.is_hidden("#synthetic-controls")
        page.fill("#open-id", str(created["session"]))
        page.click("#open")
        page.wait_for_function("document.querySelector('#session-label').textContent.includes('6 frames')")
        assert page.get_attribute("#map", "data-frames") == "6"
        # Click just past the last frame, facing +z: the memory answers with its plan.
        box = page.query_selector("#map").bounding_box()
        page.click("#map", position={"x": box["width"] / 2, "y": box["height"] * 0.75})
        page.wait_for_function("document.querySelector('#plan-source').textContent.includes('clicked')")
        thumbs = page.query_selector_all("#plan .thumb")
        assert len(thumbs) == 6, "WorldPack packs all six frames"
        assert int(page.get_attribute("#map", "data-frusta")) == 6
        assert "select" in page.inner_text("#timings")
        assert foreign == [], f"the page fetched from elsewhere: {foreign}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_the_page_sends_its_token_to_a_server_with_tokens(browser, tmp_path):
    proc, url = start(tmp_path, "--steps", "2", env={"WORLDPACK_TOKENS": "viewer:page-token"})
    try:
        page, foreign = offline_page(browser, url)
        page.goto(url + "/viewer")
        page.fill("#seed", "3")
        page.click("#create")
        page.wait_for_function("document.querySelector('#error').textContent.includes('authorization')")
        page.fill("#token", "page-token")
        page.click("#create")
        page.wait_for_function("document.querySelector('#session-label').textContent.includes('1 frame,')")
        page.keyboard.press("w")
        page.wait_for_function("document.querySelector('#frame').dataset.index === '1'")
        # The thumbnails of what the memory chose came through with the token.
        page.wait_for_function("[...document.querySelectorAll('#plan img')].length > 0 && "
                               "[...document.querySelectorAll('#plan img')].every(i => i.complete && i.naturalWidth === 64)")
        assert foreign == [], f"the page fetched from elsewhere: {foreign}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_a_session_at_224_shows_its_frames_at_224(browser, tmp_path):
    proc, url = start(tmp_path, "--steps", "2")
    try:
        page, foreign = offline_page(browser, url)
        page.goto(url + "/viewer")
        page.fill("#seed", "3")
        page.select_option("#size", "224")
        page.click("#create")
        page.wait_for_function("document.querySelector('#session-label').textContent.includes('1 frame, 224×224,')")
        page.keyboard.press("w")
        page.wait_for_function("document.querySelector('#frame').dataset.index === '1'")
        page.wait_for_function("document.querySelector('#frame').complete && document.querySelector('#frame').naturalWidth === 224")
        assert foreign == [], f"the page fetched from elsewhere: {foreign}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
