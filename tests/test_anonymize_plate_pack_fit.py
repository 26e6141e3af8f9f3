"""``regions.plate_pack_fit``: the guided plan's plate canvases are packed at the width that
makes them smallest (``pack(fit=True)``), its face canvases at the fixed width."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.anonymize.config import AnonymizeConfig
from v2xlake.tasks.anonymize.guide import Region
from v2xlake.tasks.anonymize.guided import GuidedConfig, GuidedDetector


class _Lines:
    """A text detector that records the canvases it is shown and finds nothing."""

    name = "text-stub"
    version = "0"

    def __init__(self) -> None:
        self.shapes: list[tuple[int, ...]] = []

    def lines_view(self, canvas: np.ndarray) -> list:
        self.shapes.append(canvas.shape)
        return []


def _canvases(fit: bool) -> list[tuple[int, ...]]:
    stub = _Lines()
    cfg = GuidedConfig.of(AnonymizeConfig(regions={"plate_pack_fit": fit}))
    det = GuidedDetector(None, stub, cfg)  # type: ignore[arg-type]
    # three small plate regions (no vehicle face: cropped), each cut out at 2.4x
    regions = [Region("plate", (100.0 + 200 * k, 500.0, 160.0 + 200 * k, 530.0), 40.0, f"c{k}")
               for k in range(3)]
    det.in_regions(np.zeros((1080, 1920, 3), np.uint8), regions)
    return stub.shapes


def test_plate_canvases_packed_at_the_fitting_width() -> None:
    fixed, fitted = _canvases(False), _canvases(True)
    assert len(fixed) == len(fitted) == 1
    assert fixed[0][1] == 512
    assert fitted[0][0] * fitted[0][1] < fixed[0][0] * fixed[0][1]
