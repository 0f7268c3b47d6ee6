"""The studio in a real browser (headless Chromium, software WebGL) on a simulated daemon.

Controls are found by their accessible names, as assistive technology finds them. Waits are generous and nothing
is timed: the machine may be a loaded two-core host where Chromium's software rendering takes a core.
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.client import Client, DaemonError, Telemetry
from tests._wait import wait_until

pytestmark = pytest.mark.timeout(600)


def _face(page: Any) -> np.ndarray:
    """The middle of the 3D view (where the face is) as an RGB array."""
    from PIL import Image

    box = page.locator("canvas").first.bounding_box()
    clip = {"x": box["x"] + 0.3 * box["width"], "y": box["y"] + 0.2 * box["height"],
            "width": 0.4 * box["width"], "height": 0.6 * box["height"]}
    png = page.screenshot(clip=clip)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def _changed_fraction(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean(np.abs(a - b).max(axis=2) > 24))


def _steady_face(page: Any, timeout: float = 60) -> np.ndarray:
    """The face view once it shows the same picture twice in a row (no notice, skin frame or camera move under way)."""
    shots: list[np.ndarray] = []

    def steady() -> bool:
        _dismiss_notifications(page)
        page.evaluate("() => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
        shots.append(_face(page))
        return len(shots) > 1 and np.array_equal(shots[-1], shots[-2])

    assert wait_until(steady, timeout, "a steady view", interval=0.5)
    return shots[-1]


def _dismiss_notifications(page: Any) -> None:
    """Close the client's notices (e.g. 'software WebGL') so they do not cover the view in screenshots."""
    for button in page.locator(".mantine-Notification-closeButton").all():
        with contextlib.suppress(Exception):  # already gone
            button.click(timeout=2000)


def _on_top(page: Any, locator: Any) -> bool:
    """The element is inside the viewport and is what a click at its centre would hit."""
    box = locator.bounding_box()
    view = page.viewport_size
    if box is None or box["y"] < 0 or box["y"] + box["height"] > view["height"]:
        return False
    return bool(locator.evaluate("(el, p) => el.contains(document.elementFromPoint(p[0], p[1]))",
                                 [box["x"] + box["width"] / 2, box["y"] + box["height"] / 2]))


@contextlib.contextmanager
def _counting_poses(studio: Any) -> Iterator[list[np.ndarray]]:
    """Count the studio's poses while the block runs (each call's pose, in order)."""
    calls: list[np.ndarray] = []
    original = studio.set_pose

    def counted(p: Any, source: object = None) -> Any:
        calls.append(np.array(p))
        return original(p, source)

    studio.set_pose = counted
    try:
        yield calls
    finally:
        studio.set_pose = original


def _tab(page: Any, name: str) -> None:
    page.get_by_role("tab", name=name).click()


def _status(daemon: Any) -> dict:
    with Client(daemon.command_endpoint, timeout=30) as c:
        return c.call("status")


def _inactive(daemon: Any) -> None:
    """Precondition: the daemon inactive, without a fault or e-stop left by an earlier test."""
    with Client(daemon.command_endpoint, timeout=30) as c:
        state = c.call("status")["lifecycle"]
        if state in ("fault", "estop"):
            c.call("reset")
        elif state == "active":
            c.call("disable")


def test_every_control_is_named_and_the_jaw_slider_changes_the_rendered_skin(page: Any, studio: Any,
                                                                             image_dir: Path) -> None:
    head = studio.head
    for c in head.channels:
        if c.kind in ("actuator", "group"):
            assert page.get_by_role("slider", name=c.name, exact=True).count() == 1, c.name
    assert page.get_by_role("button", name="E-stop", exact=True).is_visible()
    _tab(page, "Pose")
    page.get_by_role("button", name="Neutral pose").click()
    jaw_k = head.names.index("jaw")
    assert wait_until(lambda: abs(studio.p[jaw_k] - head.neutral[jaw_k]) < 1e-9, 30)
    assert wait_until(lambda: page.get_by_text("Accepted: within the skin's validated range").count() > 0, 30)
    _dismiss_notifications(page)
    page.wait_for_timeout(1500)
    before = _face(page)
    jaw = page.get_by_role("slider", name="jaw", exact=True)
    jaw.focus()
    page.keyboard.press("End")  # the jaw's upper limit
    assert wait_until(lambda: abs(math.degrees(studio.p[jaw_k]) - head.by_name["jaw"].max) < 1e-6, 30)
    wait_until(lambda: _changed_fraction(_face(page), before) > 0.01, 60,
               "the rendered skin to change after the jaw slider moved", interval=0.5)
    # The page draws the skin as its own smooth mesh (the subdivided surface), fed by the studio's socket.
    assert page.evaluate("Likeness.mesh.geometry.attributes.position.count") == studio.view.sub.n_vertices
    assert page.evaluate("Likeness.frames") >= 2
    # The sample head's jaw at its limit stretches the skin past the validated range: the guard says so.
    assert wait_until(lambda: page.get_by_text("Refused:").count() > 0, 30)
    page.screenshot(path=str(image_dir / "studio-pose.png"))
    # The E-stop stays in view (and on top) when the panel scrolls to its end.
    page.get_by_role("button", name="Run exact FEM pose").scroll_into_view_if_needed()
    assert _on_top(page, page.get_by_role("button", name="E-stop", exact=True))


def test_a_slider_move_reaches_the_skin_on_the_studio_socket_once(page: Any, studio: Any) -> None:
    """The page sends a slider's value on the studio's own socket ahead of viser's update; the studio poses once
    for the move (viser's later copy of the same value is recognised), and sliders it moves itself do not echo."""
    head = studio.head
    jaw_k, lid_k = head.names.index("jaw"), head.names.index("lid_l")
    _tab(page, "Pose")
    page.get_by_role("button", name="Neutral pose").click()
    assert wait_until(lambda: abs(studio.p[jaw_k] - head.neutral[jaw_k]) < 1e-9, 30)
    page.wait_for_timeout(1000)
    with _counting_poses(studio) as calls:
        page.evaluate("window.__ev = []")
        jaw = page.get_by_role("slider", name="jaw", exact=True)
        jaw.focus()
        page.keyboard.press("ArrowRight")
        assert wait_until(lambda: studio.p[jaw_k] > head.neutral[jaw_k] + 1e-6, 30)
        # viser's own update of the same move arrives later: wait until the server's slider has it.
        assert wait_until(lambda: abs(float(studio.pose_tab.sliders["jaw"].value)
                                      - math.degrees(studio.p[jaw_k])) < 1e-6, 30)
        page.wait_for_timeout(1000)
        sent = page.evaluate("window.__ev.filter(e => e[0] === 'fastsend').map(e => e[2])")
        assert sent == ["jaw"]
        assert len(calls) == 1, f"{len(calls)} poses for one slider move"
        assert abs(studio.p[lid_k] - head.neutral[lid_k]) < 1e-12
    # The key reached the slider after the skin was drawn, its release after it: viser's keyboard camera, which
    # tracks held arrow keys, saw both in order and is not left turning the view.
    _steady_face(page, 30)


def _corner(page: Any) -> np.ndarray:
    """The mean RGB of the 3D view's top-left corner, where the scene shows only its background."""
    from PIL import Image

    box = page.locator("canvas").first.bounding_box()
    png = page.screenshot(clip={"x": box["x"] + 4, "y": box["y"] + 4, "width": 40, "height": 40})
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64).reshape(-1, 3).mean(axis=0)


QUADS_SHOWN = """() => {
  let root = Likeness.mesh; while (root.parent) root = root.parent;
  const shown = [];
  root.traverse((o) => { const u = o.isMesh && o.material && o.material.uniforms;
                         if (u && u.enabled && u.colorMap && u.depthMap) shown.push(o.visible); });
  return shown;
}"""


def test_the_background_quad_is_drawn_only_while_it_has_an_image(page: Any, studio: Any) -> None:
    """viser's full-canvas background-image quad is left out of the skin's frames while it has no image (it would
    discard every pixel at a software renderer's full cost) and is drawn again once the studio sets one."""
    _tab(page, "Pose")
    assert wait_until(lambda: page.evaluate("Likeness.frames") >= 1, 60)
    assert wait_until(lambda: page.evaluate(QUADS_SHOWN) == [False], 30), page.evaluate(QUADS_SHOWN)
    blank = _corner(page)
    red = np.zeros((32, 32, 3), dtype=np.uint8)
    red[..., 0] = 255
    studio.server.scene.set_background_image(red, format="png")
    try:
        assert wait_until(lambda: _corner(page)[0] > 200 and _corner(page)[1] < 80, 30,
                          "the background image to be drawn", interval=0.3)
        assert page.evaluate(QUADS_SHOWN) == [True]
    finally:
        studio.server.scene.set_background_image(None)
    assert wait_until(lambda: np.abs(_corner(page) - blank).max() < 8, 30, "the background to clear", interval=0.3)
    assert page.evaluate(QUADS_SHOWN) == [False]


def test_the_skin_looks_the_same_with_its_tone_curve_per_vertex_or_per_pixel(page: Any, studio: Any) -> None:
    """The skin's tone curve and sRGB encoding, applied per vertex (the fast path), give the picture the renderer's
    own per-pixel ACES filmic and sRGB output gives, up to interpolation in the encoded space (largest where the
    strain colours change fastest between two vertices)."""
    head = studio.head
    jaw_k = head.names.index("jaw")
    _tab(page, "Pose")
    page.get_by_role("button", name="Neutral pose").click()
    assert wait_until(lambda: abs(studio.p[jaw_k] - head.neutral[jaw_k]) < 1e-9, 30)
    defined = "Likeness.mesh.material.defines.TONE_IN_VERTEX"

    try:
        page.evaluate("Likeness.vertexTone = false")
        assert wait_until(lambda: page.evaluate(defined) is None, 30, "the per-pixel tone curve", interval=0.3)
        per_pixel = _steady_face(page)
    finally:
        page.evaluate("Likeness.vertexTone = true")
    assert wait_until(lambda: page.evaluate(defined) == 4, 30, "the per-vertex ACES curve", interval=0.3)
    per_vertex = _steady_face(page)
    diff = np.abs(per_vertex - per_pixel).max(axis=2)
    assert per_pixel.std() > 10  # the view shows the face, not a blank canvas
    assert float(diff.mean()) < 1.5 and float(np.percentile(diff, 99)) < 12, (float(diff.mean()), int(diff.max()))


def test_a_press_on_a_slider_track_sends_the_value_the_slider_takes(page: Any, studio: Any) -> None:
    """The page computes a pressed slider's value from the pointer itself, as the slider does: the studio poses once
    (viser's own update of the press brings the same value), at the value the slider shows."""
    head = studio.head
    jaw_k = head.names.index("jaw")
    _tab(page, "Pose")
    page.get_by_role("button", name="Neutral pose").click()
    assert wait_until(lambda: abs(studio.p[jaw_k] - head.neutral[jaw_k]) < 1e-9, 30)
    _dismiss_notifications(page)
    page.wait_for_timeout(1000)
    track = page.evaluate("""() => {
        const thumb = document.querySelector('[role=slider][aria-label="jaw"]');
        const r = thumb.closest('.mantine-Slider-root').querySelector('.mantine-Slider-trackContainer')
                       .getBoundingClientRect();
        return [r.left, r.top, r.width, r.height];
    }""")
    with _counting_poses(studio) as calls:
        page.evaluate("window.__ev = []")
        page.mouse.click(track[0] + 0.3 * track[2], track[1] + track[3] / 2)  # 30 % along the track
        jaw = head.by_name["jaw"]
        assert wait_until(lambda: studio.p[jaw_k] > head.neutral[jaw_k] + 1e-6, 30)
        shown = page.get_by_role("slider", name="jaw", exact=True)
        assert wait_until(lambda: abs(float(studio.pose_tab.sliders["jaw"].value)
                                      - float(shown.get_attribute("aria-valuenow"))) < 1e-9, 30)
        page.wait_for_timeout(1000)
        value = float(shown.get_attribute("aria-valuenow"))
        assert jaw.min < value < jaw.max
        assert math.degrees(studio.p[jaw_k]) == pytest.approx(value, abs=1e-6)
        assert page.evaluate("window.__ev.filter(e => e[0] === 'fastsend').map(e => e[2])") == ["jaw"]
        assert len(calls) == 1, f"{len(calls)} poses for one press"


def test_key_two_frames_and_play_them_on_the_daemon(page: Any, studio: Any, daemon: Any, image_dir: Path) -> None:
    head = studio.head
    jaw_k = head.names.index("jaw")
    _tab(page, "Pose")
    page.get_by_role("button", name="Neutral pose").click()
    assert wait_until(lambda: abs(studio.p[jaw_k]) < 1e-9, 30)
    studio.doc.clear()
    _tab(page, "Animate")
    assert page.get_by_role("combobox", name="Channel").input_value() == "jaw"
    time_slider = page.get_by_role("slider", name="Time (s)", exact=True)
    time_slider.focus()
    page.keyboard.press("Home")
    assert wait_until(lambda: studio.animate_tab.time.value == 0.0, 30)
    page.get_by_role("button", name="Key channel").click()
    assert wait_until(lambda: studio.doc.key_times("jaw") == [0.0], 30)
    time_slider.focus()
    page.keyboard.press("End")
    assert wait_until(lambda: studio.animate_tab.time.value == pytest.approx(2.0), 30)
    _tab(page, "Pose")
    box = page.get_by_role("textbox", name="jaw value", exact=True)
    box.fill("5")  # within the strain guard's range (about 6.7° on the sample head)
    box.press("Enter")
    assert wait_until(lambda: abs(math.degrees(studio.p[jaw_k]) - 5.0) < 1e-6, 30)
    _tab(page, "Animate")
    page.get_by_role("button", name="Key channel").click()
    assert wait_until(lambda: studio.doc.key_times("jaw") == [0.0, 2.0], 30)
    assert studio.doc.to_dict()["channels"]["jaw"] == {"interp": "linear", "keys": [[0.0, 0.0], [2.0, 5.0]]}
    page.screenshot(path=str(image_dir / "studio-animate.png"))

    _tab(page, "Perform")
    _inactive(daemon)
    with Telemetry(daemon.telemetry_endpoint) as tel:
        page.get_by_role("button", name="Enable", exact=True).click()
        assert wait_until(lambda: _status(daemon)["lifecycle"] == "active", 60, interval=0.5)
        page.get_by_role("button", name="Send and play").click()
        last: list[dict] = []

        def moved(topic: str, m: dict) -> bool:
            if topic == "state":
                last[:] = [m]
            return topic == "state" and m.get("mode") == "clip" and (m["measured"].get("jaw") or 0.0) > 3.5

        seen = tel.wait_for(moved, timeout=60)
        assert seen is not None, (f"telemetry never showed the jaw following the clip; page: "
                                  f"{studio.perform_tab.reply_text.content!r}; last state: {last}")
        assert seen[1]["clip"]["name"] == "take"
        assert 3.5 < seen[1]["commanded"]["jaw"] <= 5.0 + 0.3
    assert wait_until(lambda: page.get_by_text("Playing").count() > 0, 30)
    assert wait_until(lambda: "active" in studio.perform_tab.state_text.content, 30)
    page.wait_for_timeout(1500)  # a few mirror redraws with the trace
    page.screenshot(path=str(image_dir / "studio-perform.png"))
    page.get_by_role("button", name="Disable", exact=True).click()
    assert wait_until(lambda: _status(daemon)["lifecycle"] == "inactive", 60, interval=0.5)


def test_select_a_key_on_the_timeline_and_move_it(page: Any, studio: Any, image_dir: Path) -> None:
    import json

    animate = studio.animate_tab
    studio.doc.clear()
    studio.doc.set_key("jaw", 0.0, 0.0, "linear")
    studio.doc.set_key("jaw", 2.0, 5.0)
    studio.doc.set_key("blink", 1.0, 0.5, "bezier")
    animate.channel.value = "jaw"
    animate.redraw()
    _tab(page, "Animate")
    assert wait_until(lambda: page.get_by_text("Tracks, top to bottom:").count() > 0, 30)
    page.get_by_role("combobox", name="Key", exact=True).click()
    page.get_by_role("option", name="#2 at 2.000 s").click()
    assert wait_until(lambda: animate._selected == ("jaw", 1), 30)
    assert wait_until(lambda: animate.time.value == pytest.approx(2.0), 30)  # the playhead goes to the key
    box = page.get_by_role("textbox", name="Key time (s)", exact=True)
    # The page shows the selected key before it is edited (a late update would overwrite the typed value).
    wait_until(lambda: _number(box.input_value()) == 2.0, 30, lambda: (
        f"the key-time box to show 2.0; page: time box {box.input_value()!r}, key "
        f"{page.get_by_role('combobox', name='Key', exact=True).input_value()!r}; studio: time {animate.key_t.value}, "
        f"key {animate.key_pick.value!r}, selected {animate._selected}"))
    box.fill("1.5")
    box.press("Enter")
    assert wait_until(lambda: studio.doc.key_times("jaw") == [0.0, 1.5], 30)
    box = page.get_by_role("textbox", name="Key value", exact=True)
    assert wait_until(lambda: _number(box.input_value()) == 5.0, 30)
    box.fill("4")
    box.press("Enter")
    assert wait_until(lambda: studio.doc.tracks["jaw"].keys[1].value == 4.0, 30)
    page.get_by_role("button", name="Later", exact=True).click()  # one preview frame later
    assert wait_until(lambda: studio.doc.key_times("jaw")[1] == pytest.approx(1.5 + 1 / 30), 30)
    value_box = page.get_by_role("textbox", name="Key value", exact=True)
    wait_until(lambda: value_box.input_value() == "4", 30,
               lambda: f"the key-value box to show 4, not {value_box.input_value()!r}")
    page.get_by_text("Tracks, top to bottom:").scroll_into_view_if_needed()
    page.screenshot(path=str(image_dir / "studio-timeline.png"))
    page.get_by_role("button", name="Save clip").click()
    saved = studio.options.clips_dir / "take.json"
    assert wait_until(saved.is_file, 30)
    keys = json.loads(saved.read_text())["channels"]["jaw"]["keys"]
    assert keys[0] == [0.0, 0.0] and keys[1] == [pytest.approx(1.5 + 1 / 30), 4.0]


def test_the_e_stop_reaches_the_daemon_and_reset_clears_it(page: Any, studio: Any, daemon: Any) -> None:
    _inactive(daemon)
    with Client(daemon.command_endpoint, timeout=30) as c:
        try:  # the e-stop matters most with torque on; it must latch from inactive too
            c.call("enable")
        except DaemonError:  # an emulated servo that missed its answer on a loaded host: go on from inactive
            c.call("reset")
    with Telemetry(daemon.telemetry_endpoint) as tel:
        page.get_by_role("button", name="E-stop", exact=True).click()
        event = tel.wait_for(lambda topic, m: topic == "event" and m.get("event") == "estop", timeout=30)
    assert event is not None, "the daemon published no estop event"
    assert event[1]["reason"] == "studio E-stop", event  # the page's reason travels with the shared e-stop flag
    st = _status(daemon)
    assert st["lifecycle"] == "estop" and st["estop"] == "studio E-stop"
    assert wait_until(lambda: "estop" in studio.perform_tab.state_text.content, 30)
    _tab(page, "Perform")
    page.get_by_role("button", name="Reset", exact=True).click()
    assert wait_until(lambda: _status(daemon)["lifecycle"] == "inactive", 60, interval=0.5)


def _drag(page: Any, name: str, dx: float, dy: float) -> None:
    """Drag the timeline control named ``name`` by (dx, dy) pixels with the mouse."""
    control = page.get_by_role("button", name=name, exact=True)
    # The timeline redraws from the server's state after each edit: take the box once the redrawn control is there.
    box = wait_until(control.bounding_box, 30, f"{name!r} on screen")
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + dx / 2, y + dy / 2, steps=3)
    page.mouse.move(x + dx, y + dy, steps=3)
    page.mouse.up()


def _shown_at(page: Any, name: str, t: float) -> None:
    """Wait until the timeline control ``name`` says it is at ``t`` s (its description, to the millisecond)."""
    page.wait_for_function(
        """([name, t]) => {
             const k = document.querySelector(`[aria-label="${name}"]`);
             const m = k && /^at (\\S+) s/.exec(k.getAttribute("aria-description") || "");
             return m !== null && Math.abs(parseFloat(m[1]) - t) < 1.5e-3;
           }""", arg=[name, t], timeout=30_000)


def _wav(path: Path, seconds: float, rate: int = 8000) -> Path:
    """A mono 16-bit WAV: a 220 Hz tone, loud and soft in turn every quarter second (a visible waveform)."""
    import wave

    t = np.arange(int(seconds * rate)) / rate
    loud = np.where((t * 4).astype(int) % 2 == 0, 0.8, 0.15)
    samples = (loud * np.sin(2 * np.pi * 220 * t) * 32767).astype("<i2")
    with wave.open(str(path), "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(rate)
        w.writeframes(samples.tobytes())
    return path


def test_the_timeline_edits_tracks_keys_and_handles_with_undo_and_plays_audio_with_the_head(
        page: Any, studio: Any, daemon: Any, image_dir: Path, tmp_path: Path) -> None:
    import time

    from models.clip import clip_from_dict

    doc = studio.doc
    doc.clear()
    with doc.batch():
        doc.set_key("jaw", 0.0, 0.0, "bezier")
        doc.set_key("jaw", 1.0, 4.0)
        doc.set_key("jaw", 2.0, 1.0)
        doc.set_key("blink", 0.5, 0.0, "linear")
        doc.set_key("blink", 1.5, 20.0)
    studio.animate_tab.length.value = 2.0
    studio.animate_tab.redraw()
    _tab(page, "Animate")
    page.get_by_role("button", name="jaw key 2", exact=True).wait_for()
    width = page.evaluate("document.querySelector('#likeness-timeline svg').clientWidth")
    s_per_px = 2.0 / (width - 150 - 14)  # the timeline spans the clip's 2 s right of the track names

    # Drag a key of the jaw track later and higher, then one of the blink track earlier.
    _drag(page, "jaw key 2", 40, -12)
    assert wait_until(lambda: doc.tracks["jaw"].keys[1].t != 1.0, 30)
    jaw2 = doc.tracks["jaw"].keys[1]
    assert jaw2.t == pytest.approx(1.0 + 40 * s_per_px, abs=3 * s_per_px) and jaw2.value > 4.0
    _drag(page, "blink key 1", -30, 0)
    assert wait_until(lambda: doc.tracks["blink"].keys[0].t < 0.5, 30)
    assert doc.tracks["blink"].keys[0].t == pytest.approx(0.5 - 30 * s_per_px, abs=3 * s_per_px)
    # The keyboard moves a focused key a frame. Each server update redraws the timeline and focuses the selected key
    # (the one just dragged), so focus the other key once the page shows the drag's last update.
    _shown_at(page, "blink key 1", doc.tracks["blink"].keys[0].t)
    blink2 = page.get_by_role("button", name="blink key 2", exact=True)
    blink2.focus()
    page.keyboard.press("ArrowRight")
    assert wait_until(lambda: doc.tracks["blink"].keys[1].t == pytest.approx(1.5 + 1 / 30), 30)

    # Select the jaw's key 2: its Bezier handles show; drag the out handle up and out.
    _drag(page, "jaw key 2", 0, 0)  # a click selects
    out = page.get_by_role("button", name="jaw key 2 out handle", exact=True)
    out.wait_for()
    before = doc.handles("jaw", 1)
    _drag(page, "jaw key 2 out handle", 25, -20)
    assert wait_until(lambda: doc.handles("jaw", 1) != before, 30)
    after = doc.handles("jaw", 1)
    assert after[:2] == before[:2] and after[2] > before[2] and after[3] > 0  # the in handle stays
    clip_from_dict(doc.to_dict())  # the daemon accepts the edited clip
    edited = doc.to_dict()

    # Undo takes the handle edit back, redo repeats it.
    page.get_by_role("button", name="Undo", exact=True).click()
    assert wait_until(lambda: doc.handles("jaw", 1) == before, 30)
    page.get_by_role("button", name="Redo", exact=True).click()
    assert wait_until(lambda: doc.to_dict() == edited, 30)

    # Audio: load a WAV in the browser; its waveform shows and the timeline spans it.
    wav = _wav(tmp_path / "line.wav", 8.0)  # outlasts the checks below, so the timeline still plays at the end
    page.get_by_label("Load audio").set_input_files(str(wav))
    assert wait_until(lambda: studio.animate_tab.editor.audio is not None, 30)
    assert studio.animate_tab.editor.audio.duration == pytest.approx(8.0)
    assert page.get_by_role("img", name="Waveform of line.wav").count() == 1
    page.screenshot(path=str(image_dir / "studio-timeline-editor.png"))

    # Play from the start with the head: the daemon starts the clip at the moment the page starts the sound, and
    # the preview follows the sound's clock.
    _inactive(daemon)
    with Client(daemon.command_endpoint, timeout=30) as c:
        c.call("enable")
    page.get_by_label("Play on head").check()
    with Telemetry(daemon.telemetry_endpoint) as tel:
        page.get_by_role("button", name="Play timeline", exact=True).click()
        assert wait_until(lambda: page.evaluate("Likeness.timeline.lastPlay") is not None, 30)
        seen = tel.wait_for(lambda topic, m: topic == "state" and m.get("mode") == "clip"
                            and ((m.get("clip") or {}).get("time") or 0.0) > 0.5, timeout=30)
        wall_minus_mono = time.time() - time.monotonic()  # the daemon's clock is this host's monotonic clock
    assert seen is not None, "the daemon did not play the clip"
    played = page.evaluate("Likeness.timeline.lastPlay")
    assert played["head"] and played["audio"]
    start_wall = played["startWall"] / 1e3
    assert abs((played["at"] + wall_minus_mono) - start_wall) < 0.05  # sound and head start together
    state = seen[1]
    heard = (state["t"] + wall_minus_mono) - start_wall  # the sound's clip time when the daemon sent this state
    assert abs(state["clip"]["time"] - (played["t"] + heard)) < 0.05  # played from the page's playhead
    # The preview follows the page's audio clock (the server poses the skin at the time the page plays).
    samples = []
    for _ in range(5):
        page_t = page.evaluate("Likeness.timeline.playhead")
        samples.append(abs(page_t - float(studio.animate_tab.time.value)))
        page.wait_for_timeout(150)
    assert min(samples) < 0.2, samples
    page.get_by_role("button", name="Stop timeline", exact=True).click()
    assert wait_until(lambda: page.evaluate("Likeness.timeline.playing") is None, 30)
    _inactive(daemon)


def _number(text: str) -> float | None:
    """The number a text box shows, or None while it shows none."""
    try:
        return float(text)
    except ValueError:
        return None


_MP3_SCRIPT = """
import sys
import bpy
wav, mp3 = sys.argv[-2:]
scene = bpy.context.scene
editor = scene.sequence_editor_create()
strip = (editor.strips if hasattr(editor, "strips") else editor.sequences).new_sound("line", wav, 1, 1)
scene.frame_start, scene.frame_end = 1, strip.frame_final_end - 1
assert bpy.ops.sound.mixdown(filepath=mp3, container="MP3", codec="MP3", format="S16", bitrate=64) == {"FINISHED"}
"""


def _mp3(tmp_path: Path, seconds: float) -> Path:
    """An MP3 of the test tone, encoded by Blender's sound mixdown (its FFmpeg), or a skip where bpy is missing."""
    import subprocess
    import sys

    pytest.importorskip("bpy", reason="MP3 encoding uses Blender as a module (make install adds it where it exists)")
    wav, mp3 = _wav(tmp_path / "line.wav", seconds, rate=44100), tmp_path / "line.mp3"
    subprocess.run([sys.executable, "-c", _MP3_SCRIPT, str(wav), str(mp3)], check=True, timeout=300,
                   capture_output=True)
    return mp3


def test_an_mp3_loads_into_the_timeline(page: Any, studio: Any, tmp_path: Path) -> None:
    mp3 = _mp3(tmp_path, 3.0)
    _tab(page, "Animate")
    page.get_by_label("Load audio").set_input_files(str(mp3))
    assert wait_until(lambda: studio.animate_tab.editor.audio is not None
                      and studio.animate_tab.editor.audio.name == "line.mp3", 30)
    # An MP3 decodes to its length plus the encoder's padding (a frame of 1152 samples at each end, at most).
    assert 3.0 - 0.01 <= studio.animate_tab.editor.audio.duration <= 3.0 + 3 * 1152 / 44100
    assert page.get_by_role("img", name="Waveform of line.mp3").count() == 1
