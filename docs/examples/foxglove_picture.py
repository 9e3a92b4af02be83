"""Render docs/img/foxglove-overlays.png from a session's Foxglove overlay messages.

Not a Foxglove screenshot (the Foxglove app cannot run on a headless build machine): the
``/camera/upper/annotations`` and ``/scene`` messages of a recording are decoded with the
official foxglove-schemas-protobuf classes and drawn with matplotlib, as the layout
docs/foxglove-layout.json places them (the upper image with its annotations, the 3-D scene
seen from above, global frame). Usage::

    .venv/bin/crossfield run --scenario station --frames 2 --no-rerun -o /tmp --name fox
    .venv/bin/python docs/examples/foxglove_picture.py /tmp/fox/session.mcap docs/img/foxglove-overlays.png
"""

from __future__ import annotations

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from foxglove_schemas_protobuf.ImageAnnotations_pb2 import ImageAnnotations
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from crossfield.recording import layout as L
from crossfield.recording.reader import open_recording


def rgba(c):
    return (c.r, c.g, c.b, max(c.a, 0.25))


def main(mcap: str, png: str) -> None:
    raw: dict[str, list] = {}
    with open_recording(mcap) as rec:
        for m in rec.messages([L.image_topic("upper"), L.annotations_topic("upper"), L.TOPIC_SCENE], decode=False):
            raw.setdefault(m.topic, []).append(m)
    image = RawImage.FromString(raw[L.image_topic("upper")][-1].data)
    pixels = np.frombuffer(image.data, dtype="<u2").reshape(image.height, image.width)
    ann = ImageAnnotations.FromString(raw[L.annotations_topic("upper")][-1].data)
    fig, (ax_img, ax_3d) = plt.subplots(1, 2, figsize=(13, 5.6), gridspec_kw={"width_ratios": [1.25, 1]})
    fig.patch.set_facecolor("#1e1e24")
    # Foxglove's pixel origin is the top-left pixel's corner: imshow's extent puts it there too
    ax_img.imshow(pixels, cmap="gray", extent=(0, image.width, image.height, 0), vmax=np.percentile(pixels, 99.9))
    for c in ann.circles:
        ax_img.add_patch(plt.Circle((c.position.x, c.position.y), c.diameter / 2, fill=False,
                                    color=rgba(c.outline_color), lw=1.2))
    for t in ann.texts:
        ax_img.text(t.position.x, t.position.y, t.text, color=rgba(t.text_color), fontsize=8)
    ax_img.set_title("/camera/upper/image + /camera/upper/annotations (foxglove.ImageAnnotations)",
                     color="w", fontsize=9)
    ax_img.axis("off")
    entities = {}
    for m in raw[L.TOPIC_SCENE]:
        for e in SceneUpdate.FromString(m.data).entities:
            entities[e.id] = e
    ax_3d.set_facecolor("#2a2a33")
    for e in entities.values():
        if e.frame_id != L.FRAME_GLOBAL:
            continue  # the camera-frame controls coincide with the CMM's once mapped by /tf
        for s in e.spheres:
            ax_3d.plot(1e3 * s.pose.position.x, 1e3 * s.pose.position.y, "o", ms=5, color=rgba(s.color))
        for line in e.lines:
            xy = np.array([[1e3 * p.x, 1e3 * p.y] for p in line.points])
            ax_3d.plot(xy[:, 0], xy[:, 1], "-", lw=1.5, color=rgba(line.color))
        for t in e.texts:
            ax_3d.text(1e3 * t.pose.position.x, 1e3 * t.pose.position.y, t.text, fontsize=6.5, color=rgba(t.color))
    ax_3d.set_aspect("equal")
    ax_3d.set_xlabel("global X (mm)", color="w")
    ax_3d.set_ylabel("global Y (mm)", color="w")
    ax_3d.tick_params(colors="w", labelsize=7)
    ax_3d.set_title("/scene (foxglove.SceneUpdate), frame 'global', seen from +Z", color="w", fontsize=9)
    fig.suptitle("Decoded Foxglove overlay messages of a simulated station session, drawn with matplotlib "
                 "(not a Foxglove screenshot)", color="w", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=110, facecolor=fig.get_facecolor())


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
