"""One fixed instance palette shared by the labelled cloud, the markers and the PNG renderer.

A fixed table (not a random or hashed colour) means label 3 has the same colour in RViz, in
Foxglove, in a rendered PNG and in next week's bag. The colours are Kelly's 22 colours of
maximum contrast without white, black and grey (grey is reserved for label 0, "no instance"),
in Kelly's order so neighbouring labels differ most; his two yellows nearest vivid yellow are
swapped for a blue and a magenta and a teal fills the 20th slot (every pair >= 40 RGB apart).
"""
from __future__ import annotations

import numpy as np

__all__ = ["PALETTE", "BACKGROUND", "label_colors", "packed_rgb", "instance_color"]

BACKGROUND = (128, 128, 128)
"""Colour of label 0 (and of any label <= 0): points that belong to no instance."""

PALETTE = np.array(
    [
        (0xF3, 0xC3, 0x00),  # vivid yellow
        (0x87, 0x56, 0x92),  # strong purple
        (0xF3, 0x84, 0x00),  # vivid orange
        (0xA1, 0xCA, 0xF1),  # very light blue
        (0xBE, 0x00, 0x32),  # vivid red
        (0xC2, 0xB2, 0x80),  # greyish yellow
        (0x00, 0x88, 0x56),  # vivid green
        (0xE6, 0x8F, 0xAC),  # strong purplish pink
        (0x00, 0x67, 0xA5),  # strong blue
        (0xF9, 0x93, 0x79),  # strong yellowish pink
        (0x60, 0x4E, 0x97),  # strong violet
        (0x1F, 0x3F, 0xFF),  # vivid blue (replaces Kelly's orange yellow, too close to yellow)
        (0xB3, 0x44, 0x6C),  # strong purplish red
        (0xE0, 0x1F, 0xE0),  # vivid magenta (replaces Kelly's greenish yellow, too close to yellow)
        (0x88, 0x2D, 0x17),  # strong reddish brown
        (0x8D, 0xB6, 0x00),  # vivid yellowish green
        (0x65, 0x45, 0x22),  # deep yellowish brown
        (0xE2, 0x58, 0x22),  # vivid reddish orange
        (0x2B, 0x3D, 0x26),  # dark olive green
        (0x00, 0xA0, 0xC0),  # strong greenish blue (fills Kelly's black/white/grey slots)
    ],
    dtype=np.uint8,
)
PALETTE.setflags(write=False)

# Row 0 is the background, row i (i >= 1) the colour of label i, for table lookups.
_TABLE = np.vstack([np.array(BACKGROUND, dtype=np.uint8), PALETTE])
_TABLE.setflags(write=False)
_PACKED = (
    (_TABLE[:, 0].astype(np.uint32) << 16) | (_TABLE[:, 1].astype(np.uint32) << 8) | _TABLE[:, 2]
).astype(np.uint32)
_PACKED.setflags(write=False)


def _rows(labels: np.ndarray | int) -> np.ndarray:
    """Row of ``_TABLE`` for each label: 0 for labels <= 0, else 1 + (label - 1) % len(PALETTE)."""
    lab = np.asarray(labels).astype(np.int64, copy=False)
    return np.where(lab > 0, (lab - 1) % len(PALETTE) + 1, 0)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """uint8 RGB per label, shape ``labels.shape + (3,)`` ((N, 3) for N labels)."""
    return _TABLE[_rows(labels)]


def packed_rgb(labels: np.ndarray) -> np.ndarray:
    """uint32 ``0x00RRGGBB`` per label: the PCL/RViz ``rgb`` field once reinterpreted as float32."""
    return _PACKED[_rows(labels)]


def instance_color(label: int) -> tuple[float, float, float]:
    """``(r, g, b)`` in 0..1 for one label (markers, matplotlib)."""
    r, g, b = _TABLE[int(_rows(int(label)))]
    return (r / 255.0, g / 255.0, b / 255.0)
