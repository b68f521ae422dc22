"""The toy furniture: about twenty builders, each a group of :class:`Piece` in a local frame.

A builder returns its group with x centred on the piece, z from its back (0, at the wall)
towards its front and y up from the floor. The first piece is the main one; the others
stand on it (``support``) or are tucked under it (``under``). Builders that stand on
another piece (:func:`lamp`, :func:`cup`, :func:`book_stack`) take the point to stand at.
The room planner (:mod:`.planner`) moves groups into place with a :class:`~.primitives.Frame`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .primitives import Frame, Part, box, cm, cyl


@dataclass
class Piece:
    """A future instance: label, NYU40 class, parts and upward support surfaces (parts of
    zero height), plus what it stands on or is tucked under (pieces of the same group)."""

    label: str
    category: str
    parts: list[Part]
    tops: list[Part] = field(default_factory=list)
    support: "Piece | None" = None
    under: "Piece | None" = None

    def moved(self, frame: Frame) -> "Piece":
        return Piece(self.label, self.category, [frame.part(p) for p in self.parts],
                      [frame.part(t) for t in self.tops], self.support, self.under)


def moved_group(group: list[Piece], frame: Frame) -> list[Piece]:
    """Move a group, keeping support/tucked links pointing inside the moved group."""
    out = [p.moved(frame) for p in group]
    index = {id(p): q for p, q in zip(group, out)}
    for q in out:
        q.support = index.get(id(q.support), q.support)
        q.under = index.get(id(q.under), q.under)
    return out


def lamp(x: float, z: float, y: float) -> Piece:
    """A table lamp standing at height ``y``: foot, stem, shade."""
    return Piece("lamp", "lamp", [
        cyl(x, z, 0.07, y, y + 0.03), cyl(x, z, 0.012, y + 0.03, y + 0.25),
        cyl(x, z, 0.12, y + 0.25, y + 0.45),
    ])


def floor_lamp(rng) -> list[Piece]:
    h = cm(rng, 1.3, 1.5)
    return [Piece("floor_lamp", "lamp", [
        cyl(0.0, 0.25, 0.15, 0.0, 0.03), cyl(0.0, 0.25, 0.015, 0.03, h), cyl(0.0, 0.25, 0.2, h, h + 0.3),
    ])]


def cup(x: float, z: float, y: float) -> Piece:
    return Piece("cup", "otherprop", [cyl(x, z, 0.04, y, y + 0.1)])


def book_stack(rng, x: float, z: float, y: float) -> Piece:
    """Two to four books lying flat, each exactly on the one below."""
    parts = []
    w, d = cm(rng, 0.16, 0.24), cm(rng, 0.22, 0.3)
    for _ in range(int(rng.integers(2, 5))):
        t = cm(rng, 0.02, 0.05)
        parts.append(box(x - w / 2, y, z - d / 2, x + w / 2, y + t, z + d / 2))
        y = parts[-1].hi[1]
        w, d = w - 0.01, d - 0.01
    return Piece("books", "books", parts)


def bed(rng) -> list[Piece]:
    w = cm(rng, 1.4, 1.8) if rng.random() < 0.6 else cm(rng, 0.9, 1.0)
    d = cm(rng, 1.95, 2.1)
    top = 0.52
    bed = Piece("bed", "bed", [
        box(-w / 2, 0, 0, w / 2, 0.95, 0.06),
        box(-w / 2, 0, 0.06, w / 2, 0.3, d),
        box(-w / 2 + 0.02, 0.3, 0.06, w / 2 - 0.02, top, d - 0.02),
    ], tops=[box(-w / 2 + 0.02, top, 0.06, w / 2 - 0.02, top, d - 0.02)])
    centres = [-w / 4, w / 4] if w > 1.2 else [0.0]
    pw = min(0.6, w / len(centres) - 0.1)
    pillows = [Piece("pillow", "pillow", [box(c - pw / 2, top, 0.1, c + pw / 2, top + 0.12, 0.45)],
                      support=bed) for c in centres]
    return [bed, *pillows]


def night_stand(rng) -> list[Piece]:
    w, d, h = cm(rng, 0.4, 0.5), cm(rng, 0.35, 0.42), cm(rng, 0.5, 0.6)
    stand = Piece("night_stand", "night_stand", [box(-w / 2, 0, 0, w / 2, h, d)],
                   tops=[box(-w / 2, h, 0, w / 2, h, d)])
    light = lamp(0.0, d / 2, h)
    light.support = stand
    return [stand, light]


def dresser(rng) -> list[Piece]:
    w, d, h = cm(rng, 1.0, 1.4), cm(rng, 0.45, 0.55), cm(rng, 0.8, 0.95)
    parts = [box(-w / 2, 0, 0, w / 2, h, d)]
    step = (h - 0.1) / 3
    for k in range(3):  # drawer fronts
        y0 = 0.08 + k * step
        parts.append(box(-w / 2 + 0.04, y0, d, w / 2 - 0.04, y0 + step - 0.03, d + 0.02))
    return [Piece("dresser", "dresser", parts, tops=[box(-w / 2, h, 0, w / 2, h, d)])]


def cabinet(rng, *, tv: bool = False) -> list[Piece]:
    w, d = cm(rng, 1.0, 1.6) if tv else cm(rng, 0.7, 1.2), cm(rng, 0.4, 0.5)
    h = cm(rng, 0.45, 0.55) if tv else cm(rng, 0.6, 0.9)
    cab = Piece("cabinet", "cabinet", [
        box(-w / 2, 0, 0, w / 2, h, d),
        box(-w / 2 + 0.03, 0.05, d, -0.01, h - 0.05, d + 0.02),
        box(0.01, 0.05, d, w / 2 - 0.03, h - 0.05, d + 0.02),
    ], tops=[box(-w / 2, h, 0, w / 2, h, d)])
    if not tv:
        return [cab]
    tw, th, c = min(cm(rng, 0.8, 1.2), w - 0.1), cm(rng, 0.45, 0.65), d / 2
    television = Piece("television", "television", [
        box(-0.15, h, c - 0.08, 0.15, h + 0.02, c + 0.08),
        box(-0.03, h + 0.02, c - 0.02, 0.03, h + 0.1, c + 0.02),
        box(-tw / 2, h + 0.1, c - 0.025, tw / 2, h + 0.1 + th, c + 0.025),
    ], support=cab)
    return [cab, television]


def bookshelf(rng) -> list[Piece]:
    w, d, h = cm(rng, 0.8, 1.2), cm(rng, 0.3, 0.36), cm(rng, 1.6, 2.0)
    t, n = 0.02, int(rng.integers(3, 5))
    xi0, xi1 = -w / 2 + t, w / 2 - t
    parts = [
        box(-w / 2, 0, 0, w / 2, h, t),
        box(-w / 2, 0, t, xi0, h, d), box(xi1, 0, t, w / 2, h, d),
        box(xi0, 0, t, xi1, 0.08, d), box(xi0, h - t, t, xi1, h, d),
    ]
    levels = [0.08]
    gap = (h - t - 0.08 - (n - 1) * t) / n
    for k in range(1, n):
        y0 = round(0.08 + k * gap + (k - 1) * t, 4)
        parts.append(box(xi0, y0, t, xi1, y0 + t, d))
        levels.append(parts[-1].hi[1])
    shelf = Piece("bookshelf", "bookshelf", parts,
                   tops=[box(xi0, y, t, xi1, y, d) for y in levels])
    group = [shelf]
    for y in levels:  # a row of standing books per shelf, starting at a random side
        x, books = xi0 + 0.01, []
        end = xi0 + (xi1 - xi0) * float(rng.uniform(0.4, 0.9))
        while True:
            bt, bh = cm(rng, 0.025, 0.05), cm(rng, 0.18, min(0.28, gap - 0.04))
            bd = cm(rng, 0.15, d - t - 0.02)
            if x + bt > end:
                break
            books.append(box(x, y, d - bd, x + bt, y + bh, d))
            x += bt + 0.003
        if books:
            if rng.random() < 0.5:  # mirror the row to the other side
                books = [box(xi0 + xi1 - b.hi[0], b.lo[1], b.lo[2], xi0 + xi1 - b.lo[0], b.hi[1], b.hi[2])
                         for b in books]
            group.append(Piece("books", "books", books, support=shelf))
    return group


def sofa(rng) -> list[Piece]:
    w, d = cm(rng, 1.6, 2.2), cm(rng, 0.8, 0.95)
    arm, seat = 0.15, 0.42
    sofa = Piece("sofa", "sofa", [
        box(-w / 2, 0, 0, -w / 2 + arm, 0.62, d), box(w / 2 - arm, 0, 0, w / 2, 0.62, d),
        box(-w / 2 + arm, 0, 0, w / 2 - arm, 0.85, 0.2),
        box(-w / 2 + arm, 0, 0.2, w / 2 - arm, seat, d),
    ], tops=[box(-w / 2 + arm, seat, 0.2, w / 2 - arm, seat, d)])
    n = int(rng.integers(2, 4))
    span = (w - 2 * arm) / n
    pillows = [
        Piece("pillow", "pillow",
               [box(-w / 2 + arm + k * span + 0.05, seat, 0.2, -w / 2 + arm + (k + 1) * span - 0.05,
                     seat + 0.35, 0.32)], support=sofa)
        for k in range(n)
    ]
    return [sofa, *pillows]


def _chair() -> Piece:
    """A chair facing local +z: back at z 0..0.05, seat front at z 0.45, seat top 0.45."""
    s, leg = 0.45, 0.04
    legs = [box(x, 0, z, x + leg, 0.41, z + leg) for x in (-s / 2, s / 2 - leg) for z in (0, s - leg)]
    seat, back = box(-s / 2, 0.41, 0, s / 2, s, s), box(-s / 2, s, 0, s / 2, 0.9, 0.05)
    return Piece("chair", "chair", [*legs, seat, back])


def _tuck(chair: Piece, under: Piece, frame: Frame) -> Piece:
    tucked = chair.moved(frame)
    tucked.under = under
    return tucked


def table(rng, *, coffee: bool = False, chairs: int = 0) -> list[Piece]:
    """A table centred on the local origin, with ``chairs`` chairs (0, 2 or 4) tucked under."""
    if coffee:
        w, d, h, t, leg = cm(rng, 0.9, 1.2), cm(rng, 0.5, 0.6), cm(rng, 0.42, 0.46), 0.03, 0.04
    else:
        w, d, h, t, leg = cm(rng, 1.2, 1.6), cm(rng, 0.8, 0.9), 0.75, 0.04, 0.06
    legs = [box(x, 0, z, x + leg, h - t, z + leg)
            for x in (-w / 2 + 0.04, w / 2 - 0.04 - leg) for z in (-d / 2 + 0.04, d / 2 - 0.04 - leg)]
    table = Piece("coffee_table" if coffee else "table", "table",
                   [*legs, box(-w / 2, h - t, -d / 2, w / 2, h, d / 2)],
                   tops=[box(-w / 2, h, -d / 2, w / 2, h, d / 2)])
    group = [table]
    sides = [(2, 1, 1, -d / 2), (2, -1, -1, d / 2), (0, 1, -1, -w / 2), (0, -1, 1, w / 2)][:chairs]
    for baxis, sb, su, edge in sides:
        overlap = cm(rng, 0.12, 0.2)
        frame = Frame(baxis, sb, su, edge + sb * (overlap - 0.45), cm(rng, -0.05, 0.05))
        group.append(_tuck(_chair(), table, frame))
    return group


def desk(rng) -> list[Piece]:
    w, d, h = cm(rng, 1.2, 1.6), cm(rng, 0.6, 0.7), 0.75
    desk = Piece("desk", "desk", [
        box(-w / 2, h - 0.03, 0, w / 2, h, d),
        box(-w / 2, 0, 0, -w / 2 + 0.03, h - 0.03, d), box(w / 2 - 0.03, 0, 0, w / 2, h - 0.03, d),
        box(-w / 2 + 0.03, 0.3, 0, w / 2 - 0.03, h - 0.03, 0.02),
    ], tops=[box(-w / 2, h, 0, w / 2, h, d)])
    overlap = cm(rng, 0.12, 0.2)
    chair = _tuck(_chair(), desk, Frame(2, -1, -1, d - overlap + 0.45, cm(rng, -0.1, 0.1)))
    return [desk, chair]


def counter(rng, length: float) -> list[Piece]:
    w = min(cm(rng, 1.4, 2.4), round(length - 0.1, 2))
    return [Piece("counter", "counter", [
        box(-w / 2, 0, 0, w / 2, 0.86, 0.56), box(-w / 2, 0.86, 0, w / 2, 0.9, 0.6),
    ], tops=[box(-w / 2, 0.9, 0, w / 2, 0.9, 0.6)])]


def fridge(rng) -> list[Piece]:
    w, d, h = cm(rng, 0.6, 0.8), cm(rng, 0.62, 0.7), cm(rng, 1.7, 1.9)
    return [Piece("refrigerator", "refridgerator", [
        box(-w / 2, 0, 0, w / 2, h, d), box(w / 2 - 0.08, h / 2, d, w / 2 - 0.05, h - 0.2, d + 0.04),
    ])]


def bathtub(rng) -> list[Piece]:
    w, d, h, t = cm(rng, 1.5, 1.7), cm(rng, 0.7, 0.75), 0.55, 0.08
    return [Piece("bathtub", "bathtub", [
        box(-w / 2, 0, 0, w / 2, 0.1, d),
        box(-w / 2, 0.1, 0, w / 2, h, t), box(-w / 2, 0.1, d - t, w / 2, h, d),
        box(-w / 2, 0.1, t, -w / 2 + t, h, d - t), box(w / 2 - t, 0.1, t, w / 2, h, d - t),
    ])]


def toilet(rng) -> list[Piece]:
    return [Piece("toilet", "toilet", [
        box(-0.2, 0, 0, 0.2, 0.8, 0.12), box(-0.12, 0, 0.14, 0.12, 0.3, 0.5),
        cyl(0.0, 0.31, 0.19, 0.3, 0.42),
    ])]


def sink(rng) -> list[Piece]:
    """A pedestal wash basin and the mirror above it (flush with the wall)."""
    mw = cm(rng, 0.45, 0.6)
    return [
        Piece("sink", "sink", [cyl(0.0, 0.2, 0.08, 0, 0.7), box(-0.28, 0.7, 0, 0.28, 0.86, 0.45)],
               tops=[box(-0.28, 0.86, 0, 0.28, 0.86, 0.45)]),
        Piece("mirror", "mirror", [box(-mw / 2, 1.15, 0, mw / 2, 1.15 + cm(rng, 0.6, 0.8), 0.02)]),
    ]


def wall_shelves(rng) -> list[Piece]:
    w, y = cm(rng, 0.6, 1.0), cm(rng, 1.2, 1.5)
    shelves = Piece("shelves", "shelves", [
        box(-w / 2, y, 0, -w / 2 + 0.02, y + 0.4, 0.25), box(w / 2 - 0.02, y, 0, w / 2, y + 0.4, 0.25),
        box(-w / 2 + 0.02, y, 0, w / 2 - 0.02, y + 0.02, 0.25),
        box(-w / 2 + 0.02, y + 0.38, 0, w / 2 - 0.02, y + 0.4, 0.25),
    ], tops=[box(-w / 2 + 0.02, y + 0.02, 0, w / 2 - 0.02, y + 0.02, 0.25),
             box(-w / 2 + 0.02, y + 0.4, 0, w / 2 - 0.02, y + 0.4, 0.25)])
    return [shelves]


def picture(rng) -> list[Piece]:
    w, h = cm(rng, 0.4, 0.9), cm(rng, 0.3, 0.7)
    y = cm(rng, 1.3, 1.7) - h / 2
    return [Piece("picture", "picture", [box(-w / 2, y, 0, w / 2, y + h, 0.03)])]


def cardboard_box(rng) -> list[Piece]:
    s = cm(rng, 0.25, 0.5)
    return [Piece("box", "box", [box(-s / 2, 0, 0, s / 2, cm(rng, 0.2, 0.45), s)])]


def rug(w: float, d: float) -> list[Piece]:
    """A rug 1 mm thick lying on the floor, centred on the local origin."""
    return [Piece("rug", "floor_mat", [box(-w / 2, 0, -d / 2, w / 2, 0.001, d / 2)])]
