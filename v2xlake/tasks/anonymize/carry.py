"""Detect on key frames, carry between them: a 30 Hz camera sees nearly the same thing twice.

Why: consecutive frames of a 30 Hz camera are 33 ms apart; the networks (face and text
detector) cost ~90 % of the anonymize time, and running them on every frame mostly finds the
same faces and plates again, a few pixels further. So a camera's frames are split into *key
frames*, at most ``interval`` apart, which get the full detection (guided plan or full-frame
plan, safety pass included), and the frames between two key frames, which get:

* every detection of the key frame before **and** of the key frame after, carried to this
  frame: a detection inside a projected region of a 3D box (same instance and part in both
  frames) is moved with that region, i.e. by the ego motion and the object's own motion as
  the boxes and poses know them; any other detection (safety pass, full-frame plan) stays
  where it was, and when only one key frame has it, it is grown by ``grow`` of its size per
  key-frame interval of time distance (what moved without a box);
* a fresh detection in every region that is *new*: its (instance, part) is not in both
  neighbouring key frames (an object entering, a LiDAR cluster of another scan), so nothing
  seen only between two key frames goes unsearched.

An object found in both key frames gets its box interpolated at the frame's time (at 30 Hz
the key frames are 100 ms apart: motion is near linear); one found in only one keeps the
carried box. Pure functions of detections, regions and times; ``run.py`` schedules the
frames.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import cv2
import numpy as np

from v2xlake.tasks.anonymize.detectors import Box, Detection, by_kind, overlapping
from v2xlake.tasks.anonymize.guide import Region
from v2xlake.tasks.geometry import iou_xyxy

CARRIED = "carried"


def key_frames(t_ns: Sequence[int], interval_ns: int) -> list[bool]:
    """Which frames of one camera (time order) are detected in full: the first, the last,
    and every frame after which the next frame would lie more than ``interval_ns`` after
    the last key frame. Consecutive key frames are therefore at most ``interval_ns`` apart
    (or adjacent, where the camera's own gap is longer); ``interval_ns <= 0``: every frame."""
    n = len(t_ns)
    if interval_ns <= 0 or n <= 2:
        return [True] * n
    out = [False] * n
    out[0] = out[-1] = True
    last = int(t_ns[0])
    for i in range(1, n - 1):
        if int(t_ns[i + 1]) - last > interval_ns:
            out[i] = True
            last = int(t_ns[i])
    return out


def full_key_frames(is_key: Sequence[bool], every: int) -> list[int]:
    """For each frame of one camera (time order), the position of its *full* key frame: the
    first key frame and every ``every``-th one after it get the whole plan (the value is
    their own position), the key frames between them are *light* (``plate_windows``; the
    value is the last full key frame before them); frames that are not key frames get -1.
    ``every`` <= 1: every key frame is full."""
    out = [-1] * len(is_key)
    last, k = -1, 0
    for p, key in enumerate(is_key):
        if not key:
            continue
        if every <= 1 or k % every == 0 or last < 0:
            last = p
        out[p] = last
        k += 1
    return out


def _key(r: Region) -> tuple[str, str, str]:
    return (r.instance, r.kind, r.part)


def _at_edge(r: Region, shape: tuple[int, ...]) -> bool:
    """A region without an anchor cut by the frame edge: its box no longer moves with its
    object (a region's ``anchor``, the projected part centre, is never clipped)."""
    if r.anchor is not None:
        return False
    h, w = shape[:2]
    x0, y0, x1, y1 = r.box
    return x0 <= 1 or y0 <= 1 or x1 >= w - 1 or y1 >= h - 1


def new_regions(here: Sequence[Region], before: Sequence[Region] | None,
                after: Sequence[Region] | None, shape: tuple[int, ...],
                min_face_px: float = 0.0,
                found: tuple[Sequence[Detection], Sequence[Detection]] | None = None,
                by_object: bool = False) -> list[Region]:
    """Regions of this frame searched here: those whose (instance, kind, part) is missing
    from either neighbouring key frame (None: that key frame had no guidance), those cut
    by the frame edge here or in a key frame (the clipped box does not follow the object:
    an object entering or leaving the view, often close and fast), and face regions whose
    expected face is under ``min_face_px`` (small faces score near the threshold and
    flicker from frame to frame: each frame is its own chance to find them), unless
    ``found`` (the detections of the key frame before and after) shows a face in that
    region in both key frames: it is there, and carried here like a large one.

    ``by_object`` (``clusters.carry_by_object``): a region is known when its object's
    (``_object``: any agent's track of it) part is in either key frame, at the edge in none,
    and half of the region lies where that part was or passed between them (two agents'
    LiDARs number one car their own way, and regions come from the scan nearest in time, of
    either agent: its regions alternate between their tracks)."""
    if before is None or after is None:
        return list(here)
    seen = (_found_in(found[0], before) & _found_in(found[1], after)
            if found is not None else set())
    small = [r for r in here if r.kind == "face" and r.expected_px < min_face_px
             and not (r.instance and _key(r) in seen)]
    if small:
        rest = new_regions([r for r in here if not any(r is q for q in small)],
                           before, after, shape, by_object=by_object)
        return small + rest
    if by_object:
        def obj(r: Region) -> tuple[tuple[str, str], str]:
            return _object(r), r.part

        keyed = (*before, *after)
        edge = {obj(r) for r in keyed if _at_edge(r, shape)}
        # where each object's part was: its key-frame boxes, and between a box of the key
        # frame before and one of the key frame after, the boxes at 1/4, 1/2 and 3/4 of
        # the way (the path of an object moving on, not the box around both places: an
        # object moving diagonally would make that hold a corner it never was in)
        places: dict[tuple[tuple[str, str], str], list[Box]] = {}
        for r in keyed:
            if obj(r) not in edge:
                places.setdefault(obj(r), []).append(r.box)
        for ra in before:
            for rb in after:
                if obj(ra) == obj(rb) and obj(ra) not in edge:
                    places[obj(ra)] += [
                        tuple(float((1 - f) * u + f * v)  # type: ignore[misc]
                              for u, v in zip(ra.box, rb.box, strict=True))
                        for f in (0.25, 0.5, 0.75)]

        def carried(r: Region) -> bool:
            """Its object's part is on a key frame, and at least half of it lies in one
            place that part was in, or passed through, between the key frames. The part's
            name alone is not enough: two agents may name a car's ends the other way round
            (``_object``), and two cars may be given one object number; a region elsewhere
            in the image is another part, searched here."""
            held = places.get(obj(r))
            return bool(held) and bool(
                overlapping(np.asarray(r.box), np.asarray(held), iou=np.inf,
                            contain=0.5).any())

        return [r for r in here if not r.instance or _at_edge(r, shape) or not carried(r)]
    known = ({_key(r) for r in before if not _at_edge(r, shape)}
             & {_key(r) for r in after if not _at_edge(r, shape)})  # (the frames share a size)
    return [r for r in here if not r.instance or _key(r) not in known or _at_edge(r, shape)]


def _found_in(dets: Sequence[Detection], regions: Sequence[Region]
              ) -> set[tuple[str, str, str]]:
    """The (instance, kind, part) of every region holding one of ``dets``."""
    out = set()
    for d in dets:
        r = _region_of(d, regions)
        if r is not None:
            out.add(_key(r))
    return out


def _two_objects(d: Detection, regions: Sequence[Region]) -> bool:
    """Whether regions of two objects (``_object``) of the detection's kind hold its centre,
    the detection of a size each expects (``_fits`` within 4x)."""
    cx, cy = (d.box[0] + d.box[2]) / 2, (d.box[1] + d.box[3]) / 2
    return len({_object(r) for r in regions if r.kind == d.kind and r.instance
                and r.part != "band" and r.box[0] <= cx <= r.box[2]
                and r.box[1] <= cy <= r.box[3] and _fits(d, r, 4.0)}) > 1


def _region_of(d: Detection, regions: Sequence[Region]) -> Region | None:
    """The smallest region of the detection's kind that holds the detection's centre."""
    cx, cy = (d.box[0] + d.box[2]) / 2, (d.box[1] + d.box[3]) / 2
    best, area = None, np.inf
    for r in regions:
        if r.kind != d.kind or not r.instance:
            continue
        x0, y0, x1, y1 = r.box
        if x0 <= cx <= x1 and y0 <= cy <= y1:
            a = (x1 - x0) * (y1 - y0)
            if a < area:
                best, area = r, a
    return best


def _move(box: Box, ra: Region, rb: Region) -> Box:
    """A box found in region ``ra`` moved to where region ``rb`` (the same part, another
    frame) is: by the part's projected centre and its depth (scale), or, without anchors,
    by the region boxes themselves."""
    if ra.anchor is not None and rb.anchor is not None:
        k = rb.expected_px / max(ra.expected_px, 1e-6)
        (ax, ay), (bx, by) = ra.anchor, rb.anchor
        return (bx + (box[0] - ax) * k, by + (box[1] - ay) * k,
                bx + (box[2] - ax) * k, by + (box[3] - ay) * k)
    a, b = ra.box, rb.box
    sx = (b[2] - b[0]) / max(a[2] - a[0], 1e-6)
    sy = (b[3] - b[1]) / max(a[3] - a[1], 1e-6)
    return (b[0] + (box[0] - a[0]) * sx, b[1] + (box[1] - a[1]) * sy,
            b[0] + (box[2] - a[0]) * sx, b[1] + (box[3] - a[1]) * sy)


def _grow(box: Box, frac: float, w: int, h: int) -> Box:
    mx, my = frac * (box[2] - box[0]), frac * (box[3] - box[1])
    return (max(0.0, box[0] - mx), max(0.0, box[1] - my),
            min(float(w), box[2] + mx), min(float(h), box[3] + my))


def _union(boxes: Sequence[Box]) -> Box:
    """The smallest box holding all of ``boxes`` (at least one)."""
    return (min(b[0] for b in boxes), min(b[1] for b in boxes), max(b[2] for b in boxes),
            max(b[3] for b in boxes))


def _around(boxes: Sequence[Box], m: float, w: int, h: int) -> Box:
    """``_union(boxes)`` grown by ``m`` on each side, clipped to a ``w`` x ``h`` frame."""
    x0, y0, x1, y1 = _union(boxes)
    return (max(0.0, x0 - m), max(0.0, y0 - m), min(float(w), x1 + m), min(float(h), y1 + m))


def carry(dets: Sequence[Detection], key_regions: Sequence[Region] | None,
          regions: Sequence[Region] | None, fresh: Sequence[Region] = ()
          ) -> list[tuple[Detection, Region | None]]:
    """A key frame's detections at another frame, each with the region it moved with: the
    same (instance, kind, part) projected into both frames moves it; without one it stays
    in place (region None). None of a region searched afresh here (``fresh``: its own
    search replaces them)."""
    here = {_key(r): r for r in regions or ()}
    again = {_key(r) for r in fresh}
    out: list[tuple[Detection, Region | None]] = []
    for d in dets:
        r0 = _region_of(d, key_regions) if key_regions else None
        if r0 is not None and _key(r0) in again:
            continue
        r1 = here.get(_key(r0)) if r0 is not None else None
        if r0 is not None and r1 is not None:
            out.append((Detection(d.kind, _move(d.box, r0, r1), d.score, CARRIED), r1))
        else:
            out.append((Detection(d.kind, d.box, d.score, CARRIED), None))
    return out


def _match(p: Detection, cands: Sequence[tuple[Detection, Region | None]], used: set[int],
           reach: float | None = None) -> int | None:
    """The nearest unused candidate of the same kind and similar size (within 2x) within
    its size, or within ``reach`` pixels when given."""
    px, py = (p.box[0] + p.box[2]) / 2, (p.box[1] + p.box[3]) / 2
    ps = _size(p)
    best, best_d = None, np.inf
    for k, (q, _) in enumerate(cands):
        if k in used or q.kind != p.kind:
            continue
        qx, qy = (q.box[0] + q.box[2]) / 2, (q.box[1] + q.box[3]) / 2
        qs = _size(q)
        d = float(np.hypot(qx - px, qy - py))
        if (max(ps, qs) <= 2 * min(ps, qs) and d <= (max(ps, qs) if reach is None else reach)
                and d < best_d):
            best, best_d = k, d
    return best


PLATE_PAD_M = (0.4, 0.2)  # a plate re-searched on its vehicle face: this much face around it


def _sub_face(reg: Region, box: Box, w: int, h: int) -> Region | None:
    """The part of a rectified vehicle face around a carried plate box: the box's corners
    taken to the face plane (metres, through the face's homography), grown by
    ``PLATE_PAD_M`` (enough body around the plate for the plate-blob colour test), clipped
    to the face, and back to an image quad. None when the box does not map into the face."""
    assert reg.quad is not None and reg.size_m is not None
    fw, fh = reg.size_m
    rect = np.array([[0, 0], [fw, 0], [fw, fh], [0, fh]], np.float32)
    H = cv2.getPerspectiveTransform(rect, np.asarray(reg.quad, np.float32))
    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    pts = np.array([[[box[0], box[1]]], [[box[2], box[1]]], [[box[2], box[3]]],
                    [[box[0], box[3]]]], np.float64)
    m = cv2.perspectiveTransform(pts, Hinv).reshape(-1, 2)
    if not np.isfinite(m).all():
        return None
    x0 = max(float(m[:, 0].min()) - PLATE_PAD_M[0], 0.0)
    x1 = min(float(m[:, 0].max()) + PLATE_PAD_M[0], fw)
    y0 = max(float(m[:, 1].min()) - PLATE_PAD_M[1], 0.0)
    y1 = min(float(m[:, 1].max()) + PLATE_PAD_M[1], fh)
    if x1 - x0 < 0.1 or y1 - y0 < 0.05:
        return None
    q = cv2.perspectiveTransform(np.array([[[x0, y0]], [[x1, y0]], [[x1, y1]], [[x0, y1]]],
                                          np.float64), H).reshape(-1, 2)
    bb = (max(float(q[:, 0].min()), 0.0), max(float(q[:, 1].min()), 0.0),
          min(float(q[:, 0].max()), float(w)), min(float(q[:, 1].max()), float(h)))
    if bb[2] - bb[0] < 2 or bb[3] - bb[1] < 2:
        return None
    quad = tuple((float(u), float(v)) for u, v in q)
    return Region(reg.kind, bb, reg.expected_px, "", quad, (x1 - x0, y1 - y0), reg.part, None)


def plate_windows(found: Sequence[Detection], key_regions: Sequence[Region] | None,
                  regions: Sequence[Region], shape: tuple[int, ...]) -> list[Region]:
    """The regions a *light* key frame gives the detector: ``regions`` as they are, except
    a vehicle face on which the last full key frame (``found``, ``key_regions``) found a
    plate: it is replaced by the rectified part around each plate carried here with the
    face (``_sub_face``: the plate plus ``PLATE_PAD_M`` of body).

    Why: on key frames the text detector over whole rectified vehicle faces (~480 x 256 px
    each) was the largest single cost of the guided plan at 1080p, though a plate found
    120 ms earlier sits at a known place of its face (it is fixed to the vehicle; the face
    moves with its 3D box). A face without a plate there, a face cut by the frame edge
    (its clipped box does not follow the vehicle), one new since the full key frame, and
    every other region are searched as usual, so a plate that appears is still found."""
    if not key_regions or not regions:
        return list(regions)
    h, w = shape[:2]
    here = {_key(r): r for r in regions}
    subs: dict[int, list[Region]] = {}
    whole: set[int] = set()  # faces with a carried plate that maps nowhere: searched whole
    for d in found:
        if d.kind != "plate":
            continue
        r0 = _region_of(d, key_regions)
        r1 = here.get(_key(r0)) if r0 is not None else None
        if (r0 is None or r1 is None or r1.quad is None or r1.size_m is None
                or _at_edge(r0, shape) or _at_edge(r1, shape)):
            continue
        sub = _sub_face(r1, _move(d.box, r0, r1), w, h)
        if sub is None:
            whole.add(id(r1))
        else:
            subs.setdefault(id(r1), []).append(sub)
    out: list[Region] = []
    for r in regions:
        out += subs[id(r)] if id(r) in subs and id(r) not in whole else [r]
    return out


def _recheck(again: dict[tuple[str, ...], Region], reg: Region, box: Box, w: int, h: int
             ) -> None:
    """Queue a search where a key frame's detection was carried but not confirmed, at the
    scale its region asks for: on a vehicle face the rectified part around the carried
    plate (``_sub_face``); a face around the carried box, grown by its size on each side
    (a window band is long, a head small); anything else, its whole region."""
    if _key(reg) in again:
        return
    if reg.quad is not None and reg.size_m is not None:
        sub = _sub_face(reg, box, w, h)
        if sub is not None:
            again[(*_key(reg), *(f"{v:.0f}" for v in sub.box))] = sub
            return
    if reg.kind != "face":
        again[_key(reg)] = reg
        return
    g = _grow(box, 1.0, w, h)
    small = Region(reg.kind, g, reg.expected_px, "", None, None, reg.part, None)
    again[(*_key(reg), *(f"{v:.0f}" for v in g))] = small


def between(before: tuple[Sequence[Detection], Sequence[Region] | None, int],
            after: tuple[Sequence[Detection], Sequence[Region] | None, int],
            regions: Sequence[Region] | None, t_ns: int, grow: float,
            shape: tuple[int, ...], fresh: Sequence[Region] = ()
            ) -> tuple[list[Detection], list[Region]]:
    """The carried detections of a frame at ``t_ns`` between two key frames, each given as
    (detections, regions, time), and the regions to search again here; ``fresh``: the
    regions already searched here.

    An object found in both key frames (same kind, similar size, moved at most its size
    once carried here) gets its box interpolated at this frame's time. Where the key frames
    disagree, this frame decides: a detection of only one of them that moved with a region
    is dropped and its region (a face: the neighbourhood of the carried box) returned to be
    searched here (a flickering false detection is
    not spread over the frames between, a flickering true one is found where it shows); one
    without a region (safety pass, full-frame plan) keeps its box, grown by ``grow`` x its
    time distance in key-frame intervals (it may have moved; the other key frame may have
    missed it)."""
    (d0, r0, t0), (d1, r1, t1) = before, after
    h, w = shape[:2]
    span = max(t1 - t0, 1)
    a = min(max((t_ns - t0) / span, 0.0), 1.0)
    c0, c1 = carry(d0, r0, regions, fresh), carry(d1, r1, regions, fresh)
    used: set[int] = set()
    out: list[Detection] = []
    again: dict[tuple[str, ...], Region] = {}
    for p, reg in c0:
        k = _match(p, c1, used)
        if k is not None:
            used.add(k)
            q = c1[k][0]
            box = tuple(float((1 - a) * u + a * v) for u, v in zip(p.box, q.box, strict=True))
            out.append(Detection(p.kind, box, min(p.score, q.score), CARRIED))  # type: ignore[arg-type]
        elif reg is not None:
            _recheck(again, reg, p.box, w, h)
        else:
            out.append(Detection(p.kind, _grow(p.box, grow * a, w, h), p.score, CARRIED))
    for k, (q, reg) in enumerate(c1):
        if k in used:
            continue
        if reg is not None:
            _recheck(again, reg, q.box, w, h)
        else:
            out.append(Detection(q.kind, _grow(q.box, grow * (1 - a), w, h), q.score, CARRIED))
    out = [Detection(d.kind, _grow(d.box, 0.0, w, h), d.score, d.detector) for d in out]
    return [d for d in out if d.box[2] - d.box[0] >= 1 and d.box[3] - d.box[1] >= 1], list(
        again.values())


def _fits(d: Detection, r: Region, within: float = 2.0) -> bool:
    """Whether region ``r`` expects an object of the detection's size (within ``within``
    x): a region searched at its own scale finds it again (2x), a region of its object
    moves with it (4x: a face behind a car's window is smaller than the region expects;
    a close car's window region covering the frame, 16x larger, is not its object)."""
    size = d.box[3] - d.box[1] if d.kind == "face" else d.box[2] - d.box[0]
    return 1 / within <= size / max(r.expected_px, 1e-6) <= within


def _lidar(instance: str) -> str:
    """The LiDAR that numbered a cluster track (``lidar:<agent>:<sensor>:t<k>``, maybe
    followed by ``@o<object>``)."""
    return instance.split("@", 1)[0].rsplit(":", 1)[0]


def _object(r: Region) -> tuple[str, str]:
    """The object a region's find belongs to, and the find's kind: the object number the
    clusters of all agents' LiDARs share (``<track>@o<object>``, ``clusters.object_ids``),
    else the region's instance. The part is left out: two agents' boxes of one car may
    name its ends the other way round (a footprint's yaw is known modulo 180°)."""
    inst = r.instance
    return (inst.split("@", 1)[1] if "@" in inst else inst, r.kind)


def between_tracked(before: tuple[Sequence[Detection], Sequence[Region] | None, int],
                    after: tuple[Sequence[Detection], Sequence[Region] | None, int],
                    regions: Sequence[Region] | None, t_ns: int, grow: float,
                    window: float, shape: tuple[int, ...], fresh: Sequence[Region] = (),
                    earlier: tuple[Sequence[Detection], Sequence[Region] | None, int] | None
                    = None, unsure: list[str] | None = None,
                    zones: list[tuple[str, Box]] | None = None,
                    centre: tuple[float, float] | None = None, by_object: bool = False
                    ) -> tuple[list[Detection], list[Region], list[tuple[Region, Detection]]]:
    """``between`` for regions from LiDAR cluster tracks: the carried detections of a frame
    at ``t_ns``, the regions to search here, and fallbacks: (searched window, detection)
    pairs, the detection kept when the search of its window finds nothing of its kind.

    Why not ``between``: a cluster's box is refitted from each scan's few returns, so its
    projected part jumps by up to a metre between scans (a plate carried with it landed
    20-120 px off on the simulated 1080p clip), and a frame's regions come from the scan
    nearest in time, not moved to its time. So a detection is never moved with a region
    here; the track only pairs a key frame's detection with the other key frame's (the
    first one moved by its track's region from one key frame to the other, then the
    nearest of its kind within its size, else the nearest to where it was; never two
    detections in regions of two tracks of one LiDAR that go on in the other key frame)
    and a pair is
    interpolated between the boxes the detector found (100 ms apart at 30 Hz: near
    linear). A pair that moved more than its size is checked in a window around the
    interpolated box, which stays only where that search finds nothing (a small face 60
    px a frame was interpolated 10 px off). A detection whose region is searched afresh
    here (``fresh``: its track is new here) at its scale is left to that search; one in
    a region of another scale (a small face inside a close car's window region that
    covers the frame) is not. One without a
    partner is searched for here in a window ``window`` x its larger side around it (and
    around where its track's region puts it) on each side, at its own scale (not its
    region's: a small face the full-frame pass found inside a car's window region is not
    found by that region's search): a face crossing the narrow camera moved 90 px between
    key frames, a face behind a passing car's window 45 px a frame; a plate in the far
    band's rows by the band's own search (its scale and checks) over the window's columns
    (a 30 px band plate the window missed at its own scale). Only a detection touching
    the frame edge (an object leaving the view: its cut part scores low) is kept, grown by
    ``grow`` per key-frame interval, when that search finds nothing; inside the frame a
    detection the search does not confirm is dropped (kept, moving ones were false blurs:
    0.7 per image).

    ``earlier``: the key frame before ``before`` (detections, regions, time), or None. A
    detection of ``before`` without a partner in ``after`` that has one in ``earlier``
    (the nearest of its kind and size within ``window`` x its size) moves on at the image
    velocity of that pair (``_ahead``); where that puts it across the frame edge here (it
    left the view before ``after``), the part still in view is kept when its window
    search finds nothing: a plate leaving the narrow camera at 45 px a frame was inside
    the frame on one key frame and gone on the next, and its cut part 34 px in view was
    found neither by its window search at its own scale (121 px) nor by the edge rule (it
    touched no edge on the key frame).

    ``earlier`` pairs by object identity first (``_ahead``; ``_object``: the object number
    all agents' LiDAR tracks of one object share, ``clusters.object_ids``): a plate
    leaving the view at 100 px a frame moved 6 sizes per key interval, beyond any
    size-bounded reach, and its finds on two key frames may lie in regions of two agents'
    tracks (regions come from the scan nearest in time, of either agent). So does the
    pairing of the two key frames: a detection without a partner of its size nearby gets
    the nearest of its kind in a region of the same object (a plate found 10 px wide on
    one key frame and 22 px on the other is one plate, not two lost ones).

    ``unsure``: where given, the reasons this frame's carried result cannot be trusted are
    appended (the caller then detects the frame in full, the safe default): a detection of
    the key frame before without a partner in the key frame after and without an image
    velocity (no key frame before it, or no partner there) not in view for sure in the key
    frame after; one with an image velocity whose own box, moved on at it, grown by
    ``window`` x its size, is not inside the frame here or at the key frame after (it is
    leaving the view: judged by the find, not by its region, whose box lags a close car;
    a window at its scale missed a 64 px plate at 90 px a frame that the full detection
    found) (``in_view``: nothing bounds where it went: a plate
    1.7 sizes from the edge on the first key frame had left the view by the next, and one
    whose region came from another agent's LiDAR on the key frame before, so no track to
    pair by, moved 3 sizes per key interval and left it, each unblurred on the two frames
    between); one of the key frame after without a partner that may have entered the view
    (``may_enter``: anywhere on its way in); a pair of one track whose sizes differ more
    than 2x (one of them a piece of the object: the box between them is neither); a pair
    whose find of the key frame after lies beyond ``window`` x its size of where the image
    velocity of the find before puts it (two objects one behind the other: a face crossing
    the front camera at 150 px per key interval was paired with the next walker's face
    found where it had been, and the frames between blurred neither): such a pair is not
    made, the find before is searched for as one without a partner and the find after is
    left to another partner or searched as new.

    ``zones``: where given, for each reason in ``unsure`` the part of this frame where the
    object it concerns can be (its finds, where its track's region and its image velocity
    put it, grown by its reach, clipped to the frame; one gone or new near the edge on to
    the nearest frame edge): the stage's cheaper fallback (``clusters.carry_unsure_zones``)
    searches the regions there at their own scales and the full-frame plan over them.
    ``centre``: the camera's principal point (``_ahead``: image velocities at a constant
    velocity relative to the camera too); None: the image velocity alone.

    ``by_object`` (``clusters.carry_by_object``, with ``new_regions``' of the same name): a
    find held by regions of two objects of its kind that it fits (two cars one behind the
    other) is not left to the fresh search of one of them: which object it belongs to is
    not known (a plate of a car leaving the view at 130 px a frame lay in the front-face
    region of the parked car beside it, fresh here, and had left that region)."""
    (d0, r0, t0), (d1, r1, t1) = before, after
    doubt: list[str] = unsure if unsure is not None else []
    zone: list[tuple[str, Box]] = zones if zones is not None else []
    h, w = shape[:2]
    a = min(max((t_ns - t0) / max(t1 - t0, 1), 0.0), 1.0)
    here = {_key(r): r for r in regions or ()}
    again_keys = {_key(r) for r in fresh}
    band = next((r for r in regions or () if r.part == "band"), None)
    in_b = {_key(r): r for r in r1 or ()}

    fresh_at = {_key(r): r for r in fresh}

    def doubt_at(d: Detection, reason: str, boxes: Sequence[Box | None], m: float,
                 edge: bool = False) -> None:
        """A reason this frame is unsure, and where the object of ``d`` (the find it
        concerns) can be: ``boxes`` grown by ``m``, clipped to the frame; ``edge``: and on
        to the nearest frame edge (it entered or left the view there, when or how fast
        is not known: a face at 60 px a frame was 2 reaches past its key frame's find)."""
        doubt.append(reason)
        z = list(_around([b for b in boxes if b is not None], m, w, h))
        if edge:
            gap = [z[0], z[1], w - z[2], h - z[3]]
            k = int(np.argmin(gap))
            z[k] = (0.0, 0.0, float(w), float(h))[k]
        zone.append((d.kind, (z[0], z[1], z[2], z[3])))

    def side(dets: Sequence[Detection], rk: Sequence[Region] | None, first: bool
             ) -> list[tuple[Detection, Region | None, Region | None]]:
        out = []
        for d in dets:
            r = _region_of(d, rk) if rk else None
            if (r is not None and _key(r) in again_keys and _fits(d, r)
                    and not (by_object and _two_objects(d, rk or ()))):
                # its region is searched afresh here, at its scale; unless the find's
                # image velocity, with its reach (``window`` x its size: the velocity is
                # extrapolated, and a plate nearing the camera speeds up in the image),
                # puts it outside that region here (a close car's box lags the car: a 64
                # px plate at 90 px a frame was 7 px past its region's edge, 25 px
                # further than its velocity said, and the region's search missed it)
                ahead = (_ahead(d, earlier, t0, t_ns, window, r, centre)
                         if first and earlier is not None else None)
                fr = fresh_at.get(_key(r))
                m = window * _size(d)
                if ahead is None or (fr is not None and fr.box[0] <= ahead[0] - m
                                     and fr.box[1] <= ahead[1] - m
                                     and ahead[2] + m <= fr.box[2]
                                     and ahead[3] + m <= fr.box[3]):
                    continue
            out.append((d, r, here.get(_key(r)) if r is not None else None))
        return out

    c0, c1 = side(d0, r0, True), side(d1, r1, False)
    # the key frame before's detections as the key frame after would see them (for pairing)
    pred = [(Detection(p.kind, _move(p.box, r, in_b[_key(r)]), p.score, p.detector)
             if r is not None and _key(r) in in_b else p, None) for p, r, _ in c0]
    cand = [(q, None) for q, _, _ in c1]
    used: set[int] = set()
    out: list[Detection] = []
    again: dict[tuple[str, ...], Region] = {}
    fallback: list[tuple[Region, Detection]] = []

    def look(d: Detection, boxes: list[Box], keep: Detection | None) -> None:
        """Search a window around ``boxes`` at the size of ``d``; ``keep`` stays where
        that search finds nothing of its kind."""
        r = _window(d, boxes, window, shape, band)
        if r is None:
            if keep is not None:
                out.append(keep)
            return
        again.setdefault(("window", d.kind, "", *(f"{v:.0f}" for v in r.box)), r)
        if keep is not None:
            fallback.append((r, keep))

    def cut_by_edge(b: Box) -> bool:
        """A box cut by the frame edge (not ``_at_edge``: a vehicle face's anchored region
        is cut too as its car leaves the view)."""
        return b[0] <= 1 or b[1] <= 1 or b[2] >= w - 1 or b[3] >= h - 1

    def lost(d: Detection, rk: Region | None, reg: Region | None, k: float,
             ahead: Box | None = None) -> None:
        boxes, cut = _search_boxes(d, rk, reg, ahead, w, h)
        keep = (Detection(d.kind, _grow(d.box, grow * k, w, h), d.score, CARRIED)
                if cut_by_edge(d.box) else None)  # leaving the view: its cut part may score low
        if cut is not None and cut != ahead:  # on its way out of the view: the part in it
            keep = Detection(d.kind, _grow(cut, grow * k, w, h), d.score, CARRIED)
        look(d, boxes, keep)

    def track(r: Region | None) -> tuple[str, str] | None:
        return _object(r) if r is not None and r.instance and r.part != "band" else None

    in_a = {_key(r): r for r in r0 or ()}

    def inside(b: Box, m: float) -> bool:
        """Whether box ``b`` grown by ``m`` on each side is inside the frame."""
        return b[0] - m > 0 and b[1] - m > 0 and b[2] + m < w and b[3] + m < h

    def in_view(d: Detection, rk: Region | None, other: dict[tuple[str, str, str], Region]
                ) -> bool:
        """Whether ``d`` is in view on the other key frame for sure: its track's region
        is there with its box whole, and ``d`` moved with it, grown by its reach
        (``window`` x its size), is inside the frame (a close car's region stayed whole
        while its plate, 3.5 sizes per key interval, left the view). A plate of the far
        band (30-60 m away: it moves little in the image) where its box grown by its reach
        is inside the frame: the band is the camera's own rows, in view on every frame,
        and has no track (each far plate gone on the next key frame, far plates flicker,
        marked its frames unsure: on a 1.0 s clip the reasons "plate gone near the edge"
        fell from 67 to 20, the unsure frames from 82 to 70 of 114)."""
        if rk is not None and rk.part == "band":
            return inside(d.box, window * _size(d))
        o = other.get(_key(rk)) if rk is not None and track(rk) is not None else None
        if rk is None or o is None or cut_by_edge(o.box):
            return False
        return inside(_move(d.box, rk, o), window * _size(d))

    def reach(d: Detection, rk: Region | None, other: dict[tuple[str, str, str], Region]
              ) -> float:
        """How far ``d`` may have gone by the other key frame: ``window`` x its size, plus
        how far its track's region moved between the key frames."""
        m = window * _size(d)
        o = other.get(_key(rk)) if rk is not None and track(rk) is not None else None
        if rk is not None and o is not None:
            m += float(np.hypot((o.box[0] + o.box[2] - rk.box[0] - rk.box[2]) / 2,
                                (o.box[1] + o.box[3] - rk.box[1] - rk.box[3]) / 2))
        return m

    def may_enter(d: Detection, rk: Region | None) -> bool:
        """Whether ``d``, found in the key frame after only, may have entered the view
        between the key frames: its track's region in the key frame before is not in
        view whole, and its box grown by its reach (``reach``) touches the edge."""
        if in_view(d, rk, in_a):
            return False
        return not inside(d.box, reach(d, rk, in_a))

    keys_a = {track(r) for r in r0 or ()} - {None}
    keys_b = {track(r) for r in r1 or ()} - {None}
    for k, (p, rk, reg) in enumerate(c0):
        # two tracks' detections are not one object's, where both tracks are one LiDAR's
        # (another agent's LiDAR numbers the same car its own way) and go on in the other
        # key frame (a track that broke between them says nothing)
        tp = track(rk)
        other = {j for j, (_q, rq, _) in enumerate(c1)
                 if tp is not None and rk is not None and rq is not None
                 and (tq := track(rq)) is not None and tp != tq
                 and (tp in keys_b or tq in keys_a)
                 and _lidar(rk.instance) == _lidar(rq.instance)}
        j = _match(pred[k][0], cand, used | other)
        if j is None and pred[k][0] is not p:
            j = _match(p, cand, used | other)  # the region jumped, the object did not
        if j is None and tp is not None:  # one track's find of its kind: the same object
            j = _nearest(p, [(q, None) if track(rq) == tp else (None, None)
                             for q, rq, _ in c1], used)
            if j is not None and max(_size(p), _size(c1[j][0])) > 2 * min(
                    _size(p), _size(c1[j][0])):
                doubt_at(p, f"{p.kind} of one track found at {_size(p):.0f} and "
                         f"{_size(c1[j][0]):.0f} px",
                         [p.box, c1[j][0].box],
                         window * max(_size(p), _size(c1[j][0])))
        ahead = _ahead(p, earlier, t0, t_ns, window, rk, centre) if earlier else None
        at_b = _ahead(p, earlier, t0, t1, window, rk, centre) if earlier else None
        moved = (_move(p.box, rk, reg) if rk is not None and reg is not None
                 and _fits(p, rk, 4.0) else None)
        m = window * _size(p)
        if j is not None and at_b is not None:
            q = c1[j][0]
            qx, qy = (q.box[0] + q.box[2]) / 2, (q.box[1] + q.box[3]) / 2
            if not (at_b[0] - m <= qx <= at_b[2] + m and at_b[1] - m <= qy <= at_b[3] + m):
                # its partner is not where its image velocity goes: another object (one
                # walker behind another) or another velocity; either way not known here.
                # Not paired: searched for as without a partner, the other find left to
                # another partner or searched as new
                doubt_at(p, f"{p.kind} of {_size(p):.0f} px paired against its velocity",
                         [p.box, q.box, ahead, at_b], m)
                j = None
        if j is None:
            if ahead is not None and not all(inside(b, window * _size(p))
                                             for b in (ahead, at_b or ahead)):
                # its own box at its image velocity (not its region's: a close car's box
                # lags the car) near the edge here or by the key frame after: it left the
                # view between them, where a window at its scale missed a 64 px plate at
                # 90 px a frame that the full detection found
                doubt_at(p, f"{p.kind} of {_size(p):.0f} px leaving the view at its velocity",
                         [p.box, ahead, at_b], window * _size(p))
            elif not in_view(p, rk, in_b):
                # with a velocity too: it is extrapolated from two key frames' finds, and
                # a region not surely in view was the rule before it (kept: the safe side)
                doubt_at(p, f"{p.kind} of {_size(p):.0f} px gone near the edge"
                         + ("" if ahead is not None else ", no velocity"),
                         [p.box, moved, ahead, at_b], reach(p, rk, in_b), True)
            lost(p, rk, reg, a, ahead)
            continue
        used.add(j)
        q = c1[j][0]
        box = tuple(float((1 - a) * u + a * v) for u, v in zip(p.box, q.box, strict=True))
        d = Detection(p.kind, box, min(p.score, q.score), CARRIED)  # type: ignore[arg-type]
        size = max(p.box[2] - p.box[0], p.box[3] - p.box[1])
        if np.hypot(q.box[0] + q.box[2] - p.box[0] - p.box[2],
                    q.box[1] + q.box[3] - p.box[1] - p.box[3]) / 2 > size:
            look(d, [d.box], d)  # fast: the interpolated box checked where it went
        else:
            out.append(d)
    for j, (q, rk, reg) in enumerate(c1):
        if j not in used:
            if may_enter(q, rk):
                doubt_at(q, f"{q.kind} of {_size(q):.0f} px new near the edge", [q.box],
                         reach(q, rk, in_a), True)
            lost(q, rk, reg, 1 - a)
    out = [Detection(d.kind, _grow(d.box, 0.0, w, h), d.score, d.detector) for d in out]
    return ([d for d in out if d.box[2] - d.box[0] >= 1 and d.box[3] - d.box[1] >= 1],
            list(again.values()), fallback)


def zone_regions(regions: Sequence[Region] | None, zones: Sequence[tuple[str, Box]],
                 shape: tuple[int, ...], skip: Sequence[Region] = ()) -> list[Region]:
    """The regions of a frame the full detection would search where carrying is unsure
    (``between_tracked``'s ``zones``: (kind, box)), each at its own scale but only where it
    overlaps a zone of its kind, once around all its zones: a vehicle face the part of it
    around them (``_sub_face``: its rectified plane, plus ``PLATE_PAD_M``), any other region
    its box within them; none of those in ``skip`` (searched here already), nor the far band:
    its plates are carried as on any frame between key frames (``clusters.carry_band``;
    cut to a zone's columns, the band's plate-blob test found 6 false plates on a 1.0 s
    clip that the whole band does not)."""
    h, w = shape[:2]
    out: list[Region] = []
    skipped = {id(r) for r in skip}
    for r in regions or ():
        if id(r) in skipped or r.part == "band":
            continue
        over = [(max(r.box[0], z[0]), max(r.box[1], z[1]), min(r.box[2], z[2]),
                 min(r.box[3], z[3])) for k, z in zones if k == r.kind]
        over = [b for b in over if b[2] > b[0] and b[3] > b[1]]
        if not over:
            continue
        # once per region, around all its zones (overlapping zones: one search)
        b = _union(over)
        if r.quad is not None and r.size_m is not None:
            sub = _sub_face(r, b, w, h)
            out.append(sub if sub is not None else r)
        else:
            out.append(dataclasses.replace(r, box=b))
    return out


@dataclasses.dataclass(frozen=True)
class UnsurePlan:
    """Where an unsure frame between key frames is searched as the full detection would
    (``clusters.carry_unsure_zones``): ``look`` the regions (at their own scales), ``plan_at``
    the parts the full-frame plan covers, ``doubt`` the unsure objects' zones (a fallback in
    one of its kind is dropped when the search there finds nothing: :func:`unsure_kept`)."""

    look: list[Region]
    plan_at: list[Box]
    doubt: list[tuple[str, Box]]


def unsure_plan(zones: Sequence[tuple[str, Box]], again: Sequence[Region],
                fresh: Sequence[Region], regions: Sequence[Region] | None,
                shape: tuple[int, ...]) -> UnsurePlan:
    """The searches of a frame where carrying is unsure of an object (``zones``:
    ``between_tracked``'s, (kind, box)), beside the carried frame's own (``again``: windows
    searched afresh, ``fresh``: regions new to both key frames):

    * the full-frame plan over the unsure zones;
    * a plate's window (``again``) at the plate's own scale, and the vehicle faces under it at
      theirs: a 67 px plate moving 86 px per key interval was found in its window as two
      halves of its text line, counted lost;
    * the regions cut by the frame's side edges, whole (the entry strips: an object entering
      or leaving the view shows a plate or face there that neither key frame may have seen; a
      58 / 22 px cut plate on the narrow camera at 33 / 67 ms that every frame in full found,
      on neither key frame);
    * the regions there at their own scales (:func:`zone_regions`)."""
    doubt = list(zones)
    wider = [*doubt, *((r.kind, r.box) for r in again if r.kind == "plate" and r.quad is None)]
    width = shape[1]
    skip = [*fresh, *(r for r in regions or () if r.part != "band"
                      and (r.box[0] <= 1 or r.box[2] >= width - 1))]
    look = [*skip, *again, *zone_regions(regions, wider, shape, skip)]
    return UnsurePlan(look, [z for _k, z in doubt], doubt)


def unsure_kept(fallback: Sequence[tuple[Region, Detection]], near: Sequence[Detection],
                doubt: Sequence[tuple[str, Box]]) -> list[Detection]:
    """The fallbacks of an unsure frame that stay: those :func:`unconfirmed` keeps (a cut part
    may score low), less any in an unsure zone of its kind, searched there as the full
    detection would and found empty (objects gone from the view, blurred at the edge as
    67-300 px boxes on a 1.0 s clip)."""
    return [d for d in unconfirmed(fallback, near) if not any(
        k == d.kind and z[0] <= (d.box[0] + d.box[2]) / 2 <= z[2]
        and z[1] <= (d.box[1] + d.box[3]) / 2 <= z[3] for k, z in doubt)]


def key_windows(before: tuple[Sequence[Detection], Sequence[Region] | None, int],
                earlier: tuple[Sequence[Detection], Sequence[Region] | None, int] | None,
                regions: Sequence[Region] | None, t_ns: int, window: float,
                shape: tuple[int, ...], speed_mps: float = 0.0,
                size_m: tuple[float, float] = (0.23, 0.52)) -> list[Region]:
    """The searches a key frame of a LiDAR-only clip gets *instead of* the full-frame plan
    (``clusters.full_frame_every``): a window (``_window``: ``window`` x its larger side on
    each side, at its own size) around each detection of the key frame before (``before``:
    detections, regions, time), around where its track's region moves it, and around
    where its image velocity from the key frame before that (``earlier``, ``_ahead``) puts
    it at ``t_ns``; none for a detection whose track's region is here at its scale and
    not cut by the frame edge (that region's own search finds it), nor for a plate of the
    far band (the band is searched whole on every key frame: searched only over the
    columns of the key frame before's band plates, as between key frames, 4 of 269
    plates were lost on a simulated clip, far plates the band had not held before).

    Why: the full-frame plan is the safety pass of a LiDAR-only key frame because cluster
    regions miss objects (merged, partial or missing clusters), and it is most of a key
    frame's time. What it found that no region covers is still where the key frame before
    found it, a few pixels further: the windows find it again at its own scale, and the
    key frames that keep the full-frame plan find what is new.

    ``speed_mps``: the window also reaches as far sideways as an object crossing the view
    at this speed moves in the time since the key frame before (at its depth, from its
    size: ``size_m`` a face's height, a plate's width): a 22 px face crossing the narrow
    camera moved 87 px (4 sizes) in 100 ms, beyond a window of 2 sizes, and without a
    key frame before that no velocity put it there."""
    d0, r0, t0 = before
    dt = max(t_ns - t0, 0) / 1e9
    h, w = shape[:2]
    here = {_key(r): r for r in regions or ()}
    band = next((r for r in regions or () if r.part == "band"), None)
    out: dict[tuple[str, ...], Region] = {}
    for d in d0:
        rk = _region_of(d, r0) if r0 else None
        reg = here.get(_key(rk)) if rk is not None else None
        if rk is not None and rk.part == "band" and band is not None:
            continue  # the far band is searched whole here
        if (rk is not None and reg is not None and _fits(d, rk) and not _at_edge(rk, shape)
                and not _at_edge(reg, shape)):
            continue  # its track's region is searched here at its scale
        ahead = _ahead(d, earlier, t0, t_ns, window, rk) if earlier is not None else None
        boxes, _cut = _search_boxes(d, rk, reg, ahead, w, h)
        if speed_mps > 0:
            px = d.box[3] - d.box[1] if d.kind == "face" else d.box[2] - d.box[0]
            m = speed_mps * dt * px / (size_m[0] if d.kind == "face" else size_m[1])
            boxes += [(d.box[0] - m, d.box[1], d.box[2] - m, d.box[3]),
                      (d.box[0] + m, d.box[1], d.box[2] + m, d.box[3])]
        r = _window(d, boxes, window, shape, band)
        if r is not None:
            out.setdefault(("window", d.kind, *(f"{v:.0f}" for v in r.box)), r)
    return list(out.values())


def _search_boxes(d: Detection, rk: Region | None, reg: Region | None, ahead: Box | None,
                  w: int, h: int) -> tuple[list[Box], Box | None]:
    """Where to look for ``d`` of another frame: where it was, where its track's region
    (``rk`` then, ``reg`` here) moves it when it fits that region, and the part in view of
    where its image velocity puts it (``ahead``, from ``_ahead``), returned too (None when
    that is outside the frame). Shared by the frames between key frames
    (``between_tracked``) and the key frames without the full-frame plan (``key_windows``)."""
    boxes = [d.box]
    if rk is not None and reg is not None and _fits(d, rk, 4.0):
        boxes.append(_move(d.box, rk, reg))
    cut = _grow(ahead, 0.0, w, h) if ahead is not None else None
    if cut is not None and (cut[2] - cut[0] < 1 or cut[3] - cut[1] < 1):
        cut = None
    if cut is not None:
        boxes.append(cut)
    return boxes, cut


def _window(d: Detection, boxes: Sequence[Box], window: float, shape: tuple[int, ...],
            band: Region | None) -> Region | None:
    """The region searching for ``d`` around ``boxes``: ``window`` x its larger side on
    each side, at its own size (a face's height, a plate's width); a plate in the far
    band's rows gets the band's own search (its scale, its checks) over the window's
    columns instead (at the plate's own scale a 30 px band plate was not found again).
    None when the window lies outside the frame."""
    h, w = shape[:2]
    bw, bh = d.box[2] - d.box[0], d.box[3] - d.box[1]
    # a plate moves as far up or down as sideways
    win = _around(boxes, window * max(bw, bh), w, h)
    if win[2] - win[0] < 2 or win[3] - win[1] < 2:
        return None
    cy = (d.box[1] + d.box[3]) / 2
    if band is not None and d.kind == "plate" and band.box[1] <= cy <= band.box[3]:
        return dataclasses.replace(band, box=(win[0], band.box[1], win[2], band.box[3]))
    return Region(d.kind, win, float(bh if d.kind == "face" else bw), "", None, None,
                  "head" if d.kind == "face" else "", None)


def _ahead(d: Detection, earlier: tuple[Sequence[Detection], Sequence[Region] | None, int],
           t0: int, t_ns: int, window: float, rk: Region | None = None,
           centre: tuple[float, float] | None = None) -> Box | None:
    """Where ``d`` (found at ``t0``) is at ``t_ns`` if it goes on as it came: its partner
    in the ``earlier`` key frame gives each corner's image velocity (a plate leaving the
    view also grows and drops as it nears); None without a partner. The partner: the
    nearest detection of its kind in a region of ``d``'s track (``rk``, its region at
    ``t0``: a LiDAR track is one object however far it moved: a plate leaving the view
    at 100 px a frame moved 6 sizes per key interval), else the nearest of its kind
    within 2x its size and ``window`` x its larger side (as far as a window search
    looks). Unclipped: the caller tells a box across the frame edge by it.

    ``centre``: the camera's principal point; where given, the box also holds where the
    pair puts ``d`` at a constant velocity relative to the camera (``_perspective``): an
    object nearing the camera speeds up in the image, so its image velocity is not
    constant (a 17 px face crossing the front camera moved 150 px in the 100 ms before a
    key frame and 154 px in the 67 ms after it)."""
    dets, regions, te = earlier
    if te >= t0:
        return None
    j = None
    if rk is not None and rk.instance and rk.part != "band" and regions:
        same = [(e, None) if (re := _region_of(e, regions)) is not None
                and _object(re) == _object(rk) else (None, None) for e in dets]
        j = _nearest(d, same, set())
    if j is None:
        j = _match(d, [(e, None) for e in dets], set(), window * _size(d))
    if j is None:
        return None
    k = (t_ns - t0) / (t0 - te)
    lin: Box = tuple(float(u + k * (u - v)) for u, v in zip(d.box, dets[j].box, strict=True))  # type: ignore[assignment]
    if centre is None:
        return lin
    per = _perspective(d.box, dets[j].box, k, centre)
    return _union((lin, per))


def _perspective(box: Box, before: Box, k: float, centre: tuple[float, float]) -> Box:
    """``box`` moved on ``k`` times its motion since ``before`` at a constant velocity
    relative to the camera (principal point ``centre``). Why: a pinhole camera sees a part
    of height H at lateral offset X and depth Z with a size s = f H / Z at
    c + f X / Z, so 1 / s (the depth) and (position - c) / s (the offset) are linear in
    time where X and Z are, and the image velocity of an object nearing the camera grows:
    a 17 px face crossing the front camera 150 px per 100 ms before a key frame was 70 px
    past where its image velocity put it 67 ms after (seed 1, 1.0 s, 467 ms), outside its
    window. The size grows at most 2x (as pairs are matched: a nearer extrapolation says
    the object reaches the camera plane, which the box's growth does not follow)."""
    s1 = max(box[2] - box[0], box[3] - box[1], 1e-6)
    s0 = max(before[2] - before[0], before[3] - before[1], 1e-6)
    inv = max(1 / s1 + k * (1 / s1 - 1 / s0), 0.5 / s1)
    g = 1 / (inv * s1)  # the box's growth
    m1 = ((box[0] + box[2]) / 2 - centre[0], (box[1] + box[3]) / 2 - centre[1])
    m0 = ((before[0] + before[2]) / 2 - centre[0], (before[1] + before[3]) / 2 - centre[1])
    # offsets in sizes, moved on linearly, back to pixels at the new size
    mx = (m1[0] / s1 + k * (m1[0] / s1 - m0[0] / s0)) / inv + centre[0]
    my = (m1[1] / s1 + k * (m1[1] / s1 - m0[1] / s0)) / inv + centre[1]
    hw, hh = g * (box[2] - box[0]) / 2, g * (box[3] - box[1]) / 2
    return (mx - hw, my - hh, mx + hw, my + hh)


def _nearest(p: Detection, cands: Sequence[tuple[Detection | None, Region | None]],
             used: set[int]) -> int | None:
    """The nearest unused candidate of ``p``'s kind (None entries: not candidates), at
    any distance and size: for candidates already known to be ``p``'s object (one
    track's)."""
    px, py = (p.box[0] + p.box[2]) / 2, (p.box[1] + p.box[3]) / 2
    best, best_d = None, np.inf
    for k, (q, _) in enumerate(cands):
        if q is None or k in used or q.kind != p.kind:
            continue
        dist = float(np.hypot((q.box[0] + q.box[2]) / 2 - px, (q.box[1] + q.box[3]) / 2 - py))
        if dist < best_d:
            best, best_d = k, dist
    return best


def _size(d: Detection) -> float:
    """A detection's larger side (the size ``_match`` pairs by)."""
    return max(d.box[2] - d.box[0], d.box[3] - d.box[1], 1e-6)


def unconfirmed(fallback: Sequence[tuple[Region, Detection]],
                seen: Sequence[Detection]) -> list[Detection]:
    """The fallbacks of ``between_tracked`` whose searched window holds no centre of a
    detection of their kind and size (within 2x, as ``_match`` pairs) found here: the
    carried box stays (a face or plate the window search missed is still blurred where it
    was). A smaller find does not confirm it: a 24 px plate's window search found a 9 px
    piece of its text line, and the plate was half blurred; the carried box and the piece
    are both kept."""
    return [d for r, d in fallback if not any(
        q.kind == d.kind and r.box[0] <= (q.box[0] + q.box[2]) / 2 <= r.box[2]
        and r.box[1] <= (q.box[1] + q.box[3]) / 2 <= r.box[3]
        and max(_size(q), _size(d)) <= 2 * min(_size(q), _size(d)) for q in seen)]


def merge_overlapping(dets: Sequence[Detection], iou: float = 0.3) -> list[Detection]:
    """A frame's own search results with one box per object: greedy by score (as ``nms``),
    each kept box grown to the union of the boxes of its kind it overlaps at ``iou`` or
    more, at the best score.

    Why the union: a carried frame's windows overlap (one object's window from the key
    frame before and after, moved by its track), and each finds the object with a box a
    pixel or two off: 17 boxes of 8-10 px on one 16 px face (seed 2, 0.5 s), four of 4 px
    on another's eyes counted as false blurs. Kept apart they are duplicates; the best
    scoring one alone was 1 px narrower than the face (IoU 0.29, 75 % of its box blurred);
    their union covers what each found."""
    out: list[Detection] = []
    for ds, b in by_kind(dets, out):
        ov = iou_xyxy(b, b) >= iou
        free = np.ones(len(ds), bool)
        for i, d in enumerate(ds):
            if not free[i]:
                continue
            g = free & ov[i]
            free &= ~g
            u = b[g]
            out.append(Detection(d.kind, (float(u[:, 0].min()), float(u[:, 1].min()),
                                        float(u[:, 2].max()), float(u[:, 3].max())),
                                 d.score, d.detector))
    return out
