"""Issue #24 item 2 for the anonymize stage: every setting of its numeric modules that is a user
parameter names its key in ``AnonymizeConfig`` once (tasks/anonymize/params.py) and takes its
default from there. What gets blurred must not change with that: the settings built from a
run's parameters equal the hand copies ``build.py`` made before, on the default parameters and
on a few hundred random valid ones."""

from __future__ import annotations

import random
import typing
from dataclasses import fields
from typing import Any, cast

import pytest
from pydantic import ValidationError

from v2xlake.schemas.config import Section
from v2xlake.tasks.anonymize.blur import BlurConfig
from v2xlake.tasks.anonymize.clusters import ClusterConfig
from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.detectors import ClassicPlateConfig, FaceConfig, ScanConfig
from v2xlake.tasks.anonymize.guide import GuideConfig
from v2xlake.tasks.anonymize.guided import GuidedConfig
from v2xlake.tasks.anonymize.params import DEFAULTS, FromParams, lookup
from v2xlake.tasks.anonymize.plateread import PlateReadConfig
from v2xlake.tasks.anonymize.textplate import TextPlateConfig

SETTINGS: tuple[type[FromParams], ...] = (
    GuidedConfig, GuideConfig, BlurConfig, ClusterConfig, TextPlateConfig, PlateReadConfig,
    FaceConfig, ClassicPlateConfig)
# FaceConfig's default scan before its fields named their parameters: the proposing int8
# pass is built with it, and reads only heat maps (never its scan)
OLD_FACE_SCAN = ScanConfig(max_side=1920, fine_scale=2.0, tile=2048, tile_overlap=160)


def _old_copies(cfg: AnonymizeConfig) -> dict[str, Any]:
    """What build.py built by hand before the settings named their parameters (its code
    then, verbatim but for the names, plus the plate parameter added since,
    ``edge_cut_min_aspect``; GuidedConfig's own hand copy went earlier, 72dd621)."""
    f, p, r, b, c = cfg.faces, cfg.plates, cfg.regions, cfg.blur, cfg.clusters
    scan = ScanConfig(max_side=f.max_side, fine_scale=f.fine_scale, tile=f.tile,
                      tile_overlap=f.tile_overlap, upscale_min_side=f.upscale_min_side)
    return {
        "face": FaceConfig(threshold=min(f.threshold, f.full_threshold), scan=scan,
                           quantized=f.int8),
        "first": FaceConfig(threshold=f.proposal_threshold, quantized=True, scan=OLD_FACE_SCAN),
        "plate": TextPlateConfig(
            box_threshold=p.box_threshold, min_aspect=p.min_aspect, max_aspect=p.max_aspect,
            max_tilt_deg=p.max_tilt_deg, edge_cut_min_aspect=p.edge_cut_min_aspect,
            read=PlateReadConfig(min_conf=p.read_min_conf, min_digits=p.read_min_digits,
                                 small_h=p.read_small_h, no_digit_look=p.read_no_digit_look)
            if p.read else None),
        "classic": ClassicPlateConfig(upscale=p.upscale),
        "guide": GuideConfig(margin_px=r.margin_px, margin_frac=r.margin_frac,
                             max_age_ns=int(r.box_max_age_ms * 1e6), windows=r.windows,
                             band_from_m=c.band_from_m,
                             band_min_plate_px=r.plate_text_min_px,
                             person_hold_ns=int(c.person_hold_ms * 1e6),
                             person_hold_from_m=c.dense_range_m,
                             cluster_tall_face_min_m=c.tall_face_min_m),
        "blur": BlurConfig(method=b.method, margin=b.plate_margin,
                           face_margin_x=b.face_margin_x, face_margin_top=b.face_margin_top,
                           face_margin_bottom=b.face_margin_bottom),
        "clusters": ClusterConfig(gap_deg=c.gap_deg, bridge_new_share=c.bridge_new_share,
                                  bridge_max_m=c.bridge_max_m, dense_range_m=c.dense_range_m,
                                  min_points_far=c.min_points_far,
                                  sparse_extent=c.sparse_extent,
                                  ground_isolated_m=c.ground_isolated_m,
                                  sparse_person_top_m=c.sparse_person_top_m),
        "full_face_scan": scan,
        "full_plate_scan": ScanConfig(max_side=None, fine_scale=p.full_fine_scale,
                                      tile=f.tile if p.full_fine_scale else 0,
                                      tile_overlap=f.tile_overlap, upscale_min_side=0),
    }


def _built(cfg: AnonymizeConfig) -> dict[str, Any]:
    """What build.py builds now (the proposing pass as build_detector makes it)."""
    from v2xlake.tasks.anonymize.build import blur_config, cluster_config, guide_config

    g = GuidedConfig.of(cfg)
    return {"face": FaceConfig.of(cfg),
            "first": FaceConfig(threshold=cfg.faces.proposal_threshold, quantized=True),
            "plate": TextPlateConfig.of(cfg), "classic": ClassicPlateConfig.of(cfg),
            "guide": guide_config(cfg), "blur": blur_config(cfg),
            "clusters": cluster_config(cfg), "full_face_scan": g.full_face_scan,
            "full_plate_scan": g.full_plate_scan}


def _random_value(rng: random.Random, annotation: Any, default: Any) -> Any:
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Literal:
        return rng.choice(args)
    if type(None) in args:
        if rng.random() < 0.2:
            return None
        annotation = next(a for a in args if a is not type(None))
    if annotation is bool:
        return rng.random() < 0.5
    if annotation is int:
        return rng.randint(0, 2 * max(int(default or 0), 1))
    if annotation is float:
        return rng.choice((rng.uniform(0.01, 0.99), rng.uniform(0.0, 2 * max(default or 0, 1))))
    return default


def _random_config(rng: random.Random) -> AnonymizeConfig:
    """Each parameter drawn at random within its type; a value the section refuses (its
    bounds) is drawn again, then left at its default."""
    out: dict[str, Any] = {}
    for name, top in AnonymizeConfig.model_fields.items():
        model = top.annotation
        if isinstance(model, type) and issubclass(model, Section):
            section: dict[str, Any] = {}
            for key, f in model.model_fields.items():
                for _ in range(5):
                    v = _random_value(rng, f.annotation, f.get_default(call_default_factory=True))
                    try:
                        model.model_validate({key: v})
                    except ValidationError:
                        continue
                    section[key] = v
                    break
            out[name] = section
        else:
            out[name] = _random_value(rng, top.annotation, top.default)
    return AnonymizeConfig.model_validate(out)


def _configs() -> list[AnonymizeConfig]:
    rng = random.Random(24)
    return [AnonymizeConfig(), *(_random_config(rng) for _ in range(299))]


def test_random_configs_vary_every_parameter_the_settings_read() -> None:
    """The random configs reach every path a setting names (else equality proves little)."""
    configs = _configs()
    paths = {f.metadata["param"] for cls in SETTINGS for f in fields(cast(Any, cls))
             if "param" in f.metadata}
    assert paths, "no field names a parameter"
    for path in sorted(paths):
        assert len({repr(lookup(c, path)) for c in configs}) > 1, path


def test_settings_equal_the_old_hand_copies() -> None:
    for cfg in _configs():
        old, new = _old_copies(cfg), _built(cfg)
        first_old, first_new = old.pop("first"), new.pop("first")
        assert new == old, cfg
        # the proposing pass: equal but for its scan, which it never runs
        assert (first_new.threshold, first_new.quantized, first_new.nms_iou,
                first_new.backend) == (first_old.threshold, first_old.quantized,
                                       first_old.nms_iou, first_old.backend)


def test_guided_config_is_each_named_parameter() -> None:
    """GuidedConfig.of as before (72dd621): each field naming a parameter holds it, the
    full-frame scans are built from faces / plates, every other field keeps its default."""
    plain = GuidedConfig()
    for cfg in _configs():
        g, old = GuidedConfig.of(cfg), _old_copies(cfg)
        for f in fields(g):
            want = (lookup(cfg, f.metadata["param"]) if "param" in f.metadata
                    else old[f.name] if f.name in ("full_face_scan", "full_plate_scan")
                    else getattr(plain, f.name))
            assert getattr(g, f.name) == want, (f.name, cfg)


@pytest.mark.parametrize("cls", SETTINGS, ids=lambda c: c.__name__)
def test_defaults_are_the_configs(cls: type[FromParams]) -> None:
    """One default: a setting made without parameters is the one made from the defaults."""
    assert cls() == cls.of(DEFAULTS)
    assert cls.of(AnonymizeConfig()) == cls.of(DEFAULTS)
