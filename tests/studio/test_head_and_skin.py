"""The studio's head model, strain picture, page serving and command line, on the sample head (no browser)."""

from __future__ import annotations

import math
import urllib.request

import numpy as np
import pytest

from tests.studio.conftest import SAMPLE


@pytest.fixture(scope="module")
def head():
    from studio.head import StudioHead

    return StudioHead.load(SAMPLE)


def test_channels_cover_actuators_groups_and_arkit_targets(head) -> None:
    kinds = {c.name: c.kind for c in head.channels}
    assert [n for n, k in kinds.items() if k == "actuator"] == list(head.names)
    assert {n for n, k in kinds.items() if k == "group"} == {"lip_corner_l", "lip_corner_r", "blink"}
    assert sum(k == "target" for k in kinds.values()) == 52 and kinds["arkit.jawOpen"] == "target"
    jaw = head.by_name["jaw"]
    assert (jaw.unit, jaw.min, jaw.max) == ("deg", pytest.approx(-2.0), pytest.approx(28.0))


def test_group_and_target_channels_become_actuator_poses(head) -> None:
    p = head.apply(head.neutral, {"blink": 20.0})
    lid_l, lid_r = head.names.index("lid_l"), head.names.index("lid_r")
    assert math.degrees(p[lid_l]) == pytest.approx(20.0) and math.degrees(p[lid_r]) == pytest.approx(20.0)
    clipped = head.apply(head.neutral, {"jaw": 500.0})
    assert clipped[head.names.index("jaw")] == pytest.approx(head.hi[head.names.index("jaw")])
    opened, residual = head.solve_targets({"arkit.jawOpen": 0.6}, head.neutral)
    assert opened[head.names.index("jaw")] > head.neutral[head.names.index("jaw")] + math.radians(2)
    assert residual < 0.01
    with pytest.raises(KeyError, match="unknown channel 'nose'"):
        head.apply(head.neutral, {"nose": 1.0})


def test_skin_frame_colours_strain_and_says_the_guards_verdict(head) -> None:
    from studio.skin import STRAIN_COLORS, SkinView

    view = SkinView(head)
    rest = view.frame(head.neutral)
    assert rest.passes and rest.verdict.startswith("Accepted")
    assert sum(len(f) for f in rest.band_faces) == len(view.faces)
    assert len(rest.band_faces[len(STRAIN_COLORS) - 1]) == 0  # nothing red at rest
    wide = view.frame(head.apply(head.neutral, {"jaw": 28.0}))
    assert not wide.passes and wide.verdict.startswith("Refused: stretch")
    assert wide.utilisation > 1.0 and len(wide.band_faces[len(STRAIN_COLORS) - 1]) > 0
    assert np.abs(wide.positions - rest.positions).max() > 0.005  # the jaw opened the skin by millimetres
    bands, worst, mean = view.error_bands(rest.positions + np.array([0.0, 0.0015, 0.0]), rest.positions)
    assert worst == pytest.approx(1.5, abs=1e-3) and mean == pytest.approx(1.5, abs=1e-3)
    assert len(bands[1]) == len(view.faces)  # every triangle in the 1–2 mm band


def test_the_page_is_viser_s_client_with_the_studio_script(head) -> None:
    from studio.frontdoor import FrontDoor

    door = FrontDoor("127.0.0.1", 0, ws_port=45678, title="T")
    door.start()
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{door.port}/", timeout=30) as r:
            assert r.url.endswith("/?websocket=ws://127.0.0.1:45678")
            html = r.read().decode()
        assert '<script src="/studio.js" defer></script></head>' in html and "<title>T</title>" in html
        with urllib.request.urlopen(f"http://127.0.0.1:{door.port}/studio.js", timeout=30) as r:
            assert b"aria-label" in r.read()
    finally:
        door.stop()
    # With the studio's socket, the skin and timeline scripts run first (before viser's client makes its scene),
    # each told the socket's port.
    door = FrontDoor("127.0.0.1", 0, ws_port=45678, title="T", skin_port=45999)
    door.start()
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{door.port}/?websocket=ws://127.0.0.1:45678", timeout=30) as r:
            html = r.read().decode()
        early = '<script src="/skin.js"></script><script src="/timeline.js"></script>'
        assert html.index(early) < html.index("<title>")
        for name, marker in (("skin.js", b"__THREE_DEVTOOLS__"), ("timeline.js", b"Play on head")):
            with urllib.request.urlopen(f"http://127.0.0.1:{door.port}/{name}", timeout=30) as r:
                body = r.read()
            assert body.startswith(b"window.LIKENESS_SKIN_PORT = 45999;") and marker in body
    finally:
        door.stop()


def test_serving_beyond_loopback_needs_the_head_s_opt_in() -> None:
    from likeness.cli import main
    from studio.cli.studio import check_host

    assert check_host("127.0.0.1", {}) is None and check_host("localhost", {}) is None
    assert "allow_remote" in (check_host("0.0.0.0", {"allow_remote": True}) or "")
    assert check_host("0.0.0.0", {"allow_remote": True, "insecure_remote": True}) is None
    assert main(["studio", "--config", str(SAMPLE), "--host", "0.0.0.0"]) == 2
