"""Animate tab: key channels on a timeline (step, linear, Bezier), scrub, preview at real time, save, load, import.

The clip is :class:`studio.clipdoc.ClipDoc` (the protocol's clip schema). "Key channel" keys the selected channel's
present value (from the Pose tab) at the time slider's time; "Key pose" keys every actuator. Scrubbing and preview
show the clip's pose on the predicted skin. The page's timeline editor (``static/timeline.js``, served by
:class:`studio.timeline_editor.TimelineEditor`) shows every keyed channel as a track, where keys and Bezier handles
are dragged, with undo, redo and an audio track; the "Selected key" controls here pick a key of the selected channel
and move it in time and value (typed or nudged a frame at a time) and set a Bezier key's handles.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import viser

from studio.arkit_csv import clip_from_live_link_csv
from studio.clipdoc import ClipDoc, ClipError
from studio.timeline import track_order
from studio.timeline_editor import TimelineEditor

if TYPE_CHECKING:
    from studio.app import Studio

#: Preview frame rate (Hz): the page's pose updates while a clip previews.
PREVIEW_HZ = 30.0
#: Time step of the nudge buttons (s): one preview frame.
NUDGE_S = 1.0 / PREVIEW_HZ
#: The key dropdown's entry when the selected channel has no keys.
NO_KEY = "(no keys)"


class AnimateTab:
    """The Animate tab's controls and the preview player."""

    def __init__(self, studio: Studio) -> None:
        self.studio = studio
        head = studio.head
        gui = studio.server.gui
        names = tuple(c.name for c in head.channels)
        self.name_box = gui.add_text("Clip name", initial_value=studio.doc.name)
        self.name_box.on_update(self._on_name)
        self.channel = gui.add_dropdown("Channel", options=names, initial_value=names[0])
        self.channel.on_update(lambda _: self.redraw())
        self.interp = gui.add_dropdown("Interpolation", options=("linear", "step", "bezier"), initial_value="linear")
        self.interp.on_update(self._on_interp)
        self.length = gui.add_number("Clip length (s)", initial_value=2.0, min=0.1, max=3600.0, step=0.1)
        self.length.on_update(lambda _: self._set_length(float(self.length.value)))
        self.time = gui.add_slider("Time (s)", min=0.0, max=2.0, step=0.01, initial_value=0.0)
        self.time.on_update(self._on_scrub)
        self.scrub_text = gui.add_markdown("")
        with gui.add_folder("Keys"):
            self.key_button = gui.add_button("Key channel", icon=viser.Icon.KEYFRAME,
                                             hint="Key the selected channel's present value at this time")
            self.key_button.on_click(lambda _: self.key_channel())
            self.key_pose_button = gui.add_button("Key pose", icon=viser.Icon.KEYFRAME,
                                                  hint="Key every actuator's present value at this time")
            self.key_pose_button.on_click(lambda _: self.key_pose())
            self.delete_button = gui.add_button("Delete key", icon=viser.Icon.TRASH,
                                                hint="Delete the selected channel's key at this time")
            self.delete_button.on_click(lambda _: self.delete_key())
            self.keys_text = gui.add_markdown("")
        with gui.add_folder("Tracks"):
            self.undo_button = gui.add_button("Undo edit", icon=viser.Icon.ARROW_BACK_UP, hint="Undo the last edit")
            self.undo_button.on_click(lambda _: self._history(self.studio.doc.undo))
            self.redo_button = gui.add_button("Redo edit", icon=viser.Icon.ARROW_FORWARD_UP,
                                              hint="Redo the edit last undone")
            self.redo_button.on_click(lambda _: self._history(self.studio.doc.redo))
            self.tracks_text = gui.add_markdown("")
        with gui.add_folder("Selected key"):
            self.key_pick = gui.add_dropdown("Key", options=(NO_KEY,), initial_value=NO_KEY,
                                             hint="A key of the selected channel")
            self.key_pick.on_update(self._on_pick)
            self.key_t = gui.add_number("Key time (s)", initial_value=0.0, min=0.0, max=3600.0, step=0.001)
            self.key_t.on_update(self._on_key_edit)
            self.key_v = gui.add_number("Key value", initial_value=0.0, step=0.0001)
            self.key_v.on_update(self._on_key_edit)
            self.earlier_button = gui.add_button("Earlier", icon=viser.Icon.PLAYER_TRACK_PREV,
                                                 hint="Move the selected key one frame earlier")
            self.earlier_button.on_click(lambda _: self.nudge_key(-NUDGE_S))
            self.later_button = gui.add_button("Later", icon=viser.Icon.PLAYER_TRACK_NEXT,
                                               hint="Move the selected key one frame later")
            self.later_button.on_click(lambda _: self.nudge_key(NUDGE_S))
            self.handle_boxes = tuple(gui.add_number(label, initial_value=0.0, step=0.001, visible=False)
                                      for label in ("In dt (s)", "In dv", "Out dt (s)", "Out dv"))
            for box in self.handle_boxes:
                box.on_update(self._on_handles)
            self.key_text = gui.add_markdown("")
        self._selected: tuple[str, int] | None = None
        self.editor = TimelineEditor(self)
        with gui.add_folder("Preview"):
            self.play_button = gui.add_button("Play preview", icon=viser.Icon.PLAYER_PLAY)
            self.play_button.on_click(lambda _: self.play())
            self.stop_button = gui.add_button("Stop preview", icon=viser.Icon.PLAYER_STOP)
            self.stop_button.on_click(lambda _: self.stop())
            self.loop = gui.add_checkbox("Loop preview", initial_value=False)
        with gui.add_folder("Files"):
            self.save_button = gui.add_button("Save clip", icon=viser.Icon.DEVICE_FLOPPY,
                                              hint="Write the clip as protocol JSON (clips folder) and download it")
            self.save_button.on_click(lambda event: self.save(event.client))
            self.load_button = gui.add_upload_button("Load clip (JSON)", icon=viser.Icon.UPLOAD,
                                                     mime_type="application/json")
            self.load_button.on_upload(lambda event: self._load(event.target.value))
            self.fps = gui.add_number("CSV frame rate (fps)", initial_value=60.0, min=1.0, max=1000.0, step=1.0)
            self.csv_button = gui.add_upload_button("Import ARKit CSV", icon=viser.Icon.UPLOAD, mime_type="text/csv")
            self.csv_button.on_upload(lambda event: self._import_csv(event.target.value))
            self.file_text = gui.add_markdown("")
        self._player: threading.Thread | None = None
        self._playing = threading.Event()
        self.redraw()

    # ------------------------------------------------------------------ edits
    def _on_name(self, event: viser.GuiEvent) -> None:
        if event.client_id is None:
            return
        try:
            self.studio.doc.rename(str(self.name_box.value))
        except ClipError as exc:
            self.file_text.content = f"**{exc}**"

    def _on_interp(self, event: viser.GuiEvent) -> None:
        if event.client_id is None:
            return
        ch = str(self.channel.value)
        if ch in self.studio.doc.tracks:
            self.studio.doc.set_interp(ch, str(self.interp.value))
            self.redraw()

    def present_value(self, channel: str) -> float:
        """The channel's value in the pose shown (config units)."""
        head = self.studio.head
        kind = head.kind(channel)
        slider = self.studio.pose_tab.sliders.get(channel)
        if kind == "actuator":
            return head.channel_values(self.studio.p)[channel]
        if slider is not None:
            return float(slider.value)
        return 0.0

    def key_channel(self, channel: str | None = None, t: float | None = None) -> None:
        ch = channel or str(self.channel.value)
        at = float(self.time.value) if t is None else t
        self.studio.doc.set_key(ch, at, round(self.present_value(ch), 6), str(self.interp.value)
                                if ch not in self.studio.doc.tracks else None)
        self.redraw()

    def key_pose(self) -> None:
        at = float(self.time.value)
        with self.studio.doc.batch():  # one undo step
            for name in self.studio.head.names:
                self.studio.doc.set_key(name, at, round(self.present_value(name), 6),
                                        str(self.interp.value) if name not in self.studio.doc.tracks else None)
        self.redraw()

    def delete_key(self) -> None:
        self.studio.doc.remove_key(str(self.channel.value), float(self.time.value))
        self.redraw()

    def _set_length(self, length: float) -> None:
        length = max(length, self.studio.doc.duration, 0.1)
        self.time.max = round(length, 3)
        if float(self.time.value) > length:
            self.time.value = round(length, 3)
        self.redraw()

    # ------------------------------------------------------------------ view
    def redraw(self) -> None:
        doc = self.studio.doc
        ch = str(self.channel.value)
        if doc.duration > float(self.time.max):
            self.time.max = round(doc.duration, 3)
            self.length.value = round(doc.duration, 3)
        track = doc.tracks.get(ch)
        if track is not None and str(self.interp.value) != track.interp:
            self.interp.value = track.interp
        times = doc.key_times(ch)
        self.keys_text.content = (f"`{ch}`: {len(times)} key(s), {track.interp}: "
                                  + ", ".join(f"{t:.2f} s" for t in times[:12]) + (" …" if len(times) > 12 else "")
                                  if track else f"`{ch}` has no keys. Clip: {len(doc.tracks)} channel(s), "
                                                f"{doc.duration:.2f} s.")
        self._sync_key_controls()
        self.draw_timeline()

    def _history(self, step: Any) -> None:
        with self.studio.pose_lock:
            step()
            self.redraw()

    def draw_timeline(self) -> None:
        """Publish the timeline to the page's editor and list the tracks in words."""
        doc = self.studio.doc
        self.editor.publish()
        rows = []
        for ch in track_order(doc, tuple(c.name for c in self.studio.head.channels)):
            tr = doc.tracks[ch]
            keys = ", ".join(("**" if self._selected == (ch, i) else "") + f"{k.t:.2f} s"
                             + ("**" if self._selected == (ch, i) else "") for i, k in enumerate(tr.keys[:8]))
            rows.append(f"- `{ch}` ({tr.interp}): {keys}{' …' if len(tr.keys) > 8 else ''}")
        self.tracks_text.content = ("Tracks, top to bottom:\n" + "\n".join(rows)) if rows else "No tracks yet."

    # ------------------------------------------------------------------ selected key
    def _key_label(self, i: int, t: float) -> str:
        return f"#{i + 1} at {t:.3f} s"

    def _sync_key_controls(self) -> None:
        """The key dropdown lists the selected channel's keys; the number boxes show the selected key."""
        doc = self.studio.doc
        ch = str(self.channel.value)
        track = doc.tracks.get(ch)
        if track is None:
            self._selected = None
            self.key_pick.options = (NO_KEY,)
            self.key_pick.value = NO_KEY
            for box in self.handle_boxes:
                box.visible = False
            return
        if self._selected is None or self._selected[0] != ch or self._selected[1] >= len(track.keys):
            self._selected = (ch, 0)
        i = self._selected[1]
        self.key_pick.options = tuple(self._key_label(j, k.t) for j, k in enumerate(track.keys))
        self.key_pick.value = self._key_label(i, track.keys[i].t)
        key = track.keys[i]
        self.key_t.value = round(key.t, 6)
        self.key_v.value = round(key.value, 6)
        bezier = track.interp == "bezier"
        for box in self.handle_boxes:
            box.visible = bezier
        if bezier:
            for box, h in zip(self.handle_boxes, doc.handles(ch, i), strict=True):
                box.value = round(h, 6)

    def _on_pick(self, event: viser.GuiEvent) -> None:
        if event.client_id is None or str(self.key_pick.value) == NO_KEY:
            return
        ch = str(self.channel.value)
        labels = [self._key_label(j, t) for j, t in enumerate(self.studio.doc.key_times(ch))]
        if str(self.key_pick.value) in labels:
            self.select_key(ch, labels.index(str(self.key_pick.value)))

    def select_key(self, channel: str, index: int) -> None:
        """Select key ``index`` of ``channel`` and move the playhead to it (the skin shows the clip there)."""
        t = self.studio.doc.key_times(channel)[index]
        self._selected = (channel, index)
        if t > float(self.time.max):
            self.time.max = round(t, 3)
        self.time.value = round(t, 3)
        self.key_text.content = ""
        self.redraw()
        self.show_time(float(self.time.value))

    def move_selected(self, t: float, value: float) -> None:
        """Move the selected key to time ``t`` and ``value`` (refusals are shown beside the controls)."""
        if self._selected is None:
            self.key_text.content = "**No key selected**: the selected channel has no keys."
            return
        ch, i = self._selected
        try:
            j = self.studio.doc.move_key(ch, i, round(t, 6), value)
        except ClipError as exc:
            self.key_text.content = f"**Not moved**: {exc}"
            self.redraw()
            return
        self._selected = (ch, j)
        self.key_text.content = f"Moved `{ch}` key to {t:.3f} s, value {value:.4g}."
        self.redraw()

    def nudge_key(self, dt: float) -> None:
        if self._selected is None:
            self.key_text.content = "**No key selected**: the selected channel has no keys."
            return
        ch, i = self._selected
        key = self.studio.doc.tracks[ch].keys[i]
        self.move_selected(max(0.0, key.t + dt), key.value)

    def _on_key_edit(self, event: viser.GuiEvent) -> None:
        if event.client_id is None:
            return
        self.move_selected(float(self.key_t.value), float(self.key_v.value))

    def _on_handles(self, event: viser.GuiEvent) -> None:
        if event.client_id is None or self._selected is None:
            return
        ch, i = self._selected
        h = tuple(float(b.value) for b in self.handle_boxes)
        try:
            self.studio.doc.set_handles(ch, i, (h[0], h[1], h[2], h[3]))
        except ClipError as exc:
            self.key_text.content = f"**Handles not set**: {exc}"
            self.redraw()
            return
        self.key_text.content = f"Set `{ch}` key #{i + 1}'s handles."
        self.redraw()

    def _on_scrub(self, event: viser.GuiEvent) -> None:
        if event.client_id is None:
            return
        self.show_time(float(self.time.value))

    def show_time(self, t: float, playhead: bool = True) -> None:
        """Pose the skin as the clip stands at time ``t`` (channels the clip does not key keep their values); the
        page's playhead follows unless the page itself drives it (``playhead=False``)."""
        values = self.studio.doc.sample(t)
        ch = str(self.channel.value)
        self.scrub_text.content = f"t = {t:.2f} s" + (f" · `{ch}` = {values[ch]:.3g}" if ch in values else "")
        if playhead:
            self.editor.publish_playhead(t)
        if not values:
            return
        p = self.studio.head.pose_from_channels(values, self.studio.p)
        self.studio.set_pose(p)
        targets = {k: v for k, v in values.items() if self.studio.head.by_name.get(k) is not None
                   and self.studio.head.by_name[k].kind == "target"}
        for k, v in targets.items():
            s = self.studio.pose_tab.sliders.get(k)
            if s is not None:
                s.value = round(float(v), 4)

    # ------------------------------------------------------------------ preview
    def play(self) -> None:
        if self._playing.is_set() or not self.studio.doc.tracks:
            return
        self._playing.set()
        self._player = threading.Thread(target=self._run, name="studio-preview", daemon=True)
        self._player.start()

    def stop(self) -> None:
        self._playing.clear()
        if self._player is not None:
            self._player.join(timeout=2.0)
            self._player = None

    def _run(self) -> None:
        doc = self.studio.doc
        start = time.monotonic() - float(self.time.value)
        while self._playing.is_set():
            t = time.monotonic() - start
            end = max(doc.duration, 1e-3)
            if t > end:
                if not self.loop.value:
                    self.time.value = round(end, 3)
                    self.show_time(end)
                    break
                start += end * (t // end)
                t = time.monotonic() - start
            self.time.value = round(t, 3)
            self.show_time(t)
            time.sleep(max(0.0, 1.0 / PREVIEW_HZ - (time.monotonic() - start - t)))
        self._playing.clear()

    # ------------------------------------------------------------------ files
    def save(self, client: Any = None) -> None:
        doc = self.studio.doc
        try:
            text = doc.to_json()
        except ClipError as exc:
            self.file_text.content = f"**Not saved**: {exc}"
            return
        folder = self.studio.options.clips_dir
        folder.mkdir(parents=True, exist_ok=True)
        path = doc.save(folder / f"{doc.name}.json")
        self.file_text.content = f"Saved `{path}`."
        if client is not None:
            client.send_file_download(f"{doc.name}.json", text.encode("utf-8"))

    def _load(self, upload: Any) -> None:
        try:
            doc = ClipDoc.from_json(upload.content, upload.name)
            doc.check_channels(self.studio.head.by_name)
        except ClipError as exc:
            self.file_text.content = f"**Not loaded**: {exc}"
            return
        self._replace(doc, f"Loaded `{upload.name}`")

    def _import_csv(self, upload: Any) -> None:
        try:
            text = upload.content.decode("utf-8")
            name = upload.name.rsplit(".", 1)[0] or "arkit"
            doc = clip_from_live_link_csv(text, name, fps=float(self.fps.value), source=upload.name,
                                          channels=[c.name for c in self.studio.head.channels if c.kind == "target"])
        except (ClipError, UnicodeDecodeError) as exc:
            self.file_text.content = f"**Not imported**: {exc}"
            return
        self._replace(doc, f"Imported `{upload.name}`")

    def _replace(self, doc: ClipDoc, what: str) -> None:
        self.stop()
        self.studio.doc = doc
        self.name_box.value = doc.name
        if doc.tracks:
            self.channel.value = sorted(doc.tracks)[0]
        self._set_length(max(doc.duration, 0.1))
        self.file_text.content = (f"{what}: {len(doc.tracks)} channel(s), "
                                  f"{sum(len(t.keys) for t in doc.tracks.values())} keys, {doc.duration:.2f} s.")

    def close(self) -> None:
        self.stop()
