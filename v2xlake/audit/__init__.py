"""Privacy audit of the clean zone or of a release folder: nothing identifying may leave raw.

A tool over the lake and the releases, not a stage: ``run.py`` walks a zone, release or
folder (``audit``), ``rules.py`` holds the rules on values, text and image metadata,
``points.py`` reads point files, ``bags.py`` rosbags, ``report.py`` the findings, the
error and the thresholds (``AuditConfig``). The anonymize stage's models re-check images.

What it looks for, and why each rule has the shape it has:

* absolute time: integer columns (or JSON/YAML/text numbers) whose every value lies in the
  1990-2100 epoch window in s, ms, us or ns. A column named ``*_ns`` / ``*_us`` / ``*_ms`` /
  ``*_s`` is only tested in its own unit, because a long clip's relative time in ns (6e11 ns
  = 10 min) overlaps the epoch window in ms.
* latitude/longitude: any column or JSON key named lat/lon/latitude/longitude/lng/gps*, with
  values; and, by value, a pair of float columns of one table that (1) are both tightly
  clustered (spread < ``latlon_max_spread_deg``) away from zero (|v| > 1) with many decimals,
  (2) read as degrees, span about as many metres as the clip's own ego poses do (0.2x-5x),
  and (3) are smooth in row order like a sampled trajectory. Local ENU metres of a moving clip
  spread far wider than 0.05; constant columns (calibration, a parked roadside unit) have no
  spread; the velocity of a cruising car is tightly clustered but, read as degrees, spans
  centimetres (numerically constant) or kilometres (sensor noise) and is rough. The value
  rule is skipped when the zone's ego poses show clips that hardly move (< 5 m): then
  metres and degrees cannot be told apart; the name rule still applies.
* image metadata: PNG text/EXIF/time chunks (parsed here) and JPEG APP1/COM segments.
* unblurred faces / plates: the anonymizer's detector is re-run on a sample of images;
  a detection above the audit's score threshold is a finding.
* rosbags (``.bag`` ROS 1, ``.db3`` / ``.mcap`` ROS 2; a folder with ``metadata.yaml`` is read
  as one bag, a bare storage file on its own): opened with ``rosbags.highlevel.AnyReader``,
  every message is deserialized and walked. Any ``builtin_interfaces/Time`` (header stamps,
  tf stamps) and any log time in the epoch window is absolute time; ``NavSatFix`` and any
  message with a lat/lon-named field is latitude/longitude; strings go through the text rule;
  ``PointCloud2`` fields go through the point rule below; ``Image`` / ``CompressedImage``
  messages join the dataset images the detector re-checks (one sample over files and bags).
  A bag that cannot be opened or read is an ``unreadable`` finding, never a silent skip.
* point files (``.pcd`` by its header's FIELDS/SIZE/TYPE/COUNT, ascii or binary; ``.ply``
  by its header; ``.npy``; ``.bin`` / ``.pcd.bin`` as nuScenes/KITTI write them): any value
  of any field in the epoch window in s/ms/us/ns is absolute time (an x of 1.7e9 is never a
  real point; packed ``rgb``/``rgba`` fields are colours and skipped). A ``.bin`` has no
  header: it is read as float32 (any value), and as float64 N x 3..6 where a whole column
  lies in the window (reading float32 points as float64 makes isolated values land there).
  ``binary_compressed`` PCDs are not decoded: an ``unreadable`` finding.
* everything else: a file whose extension the audit has no scanner for is an
  ``unscannable`` finding, not skipped: what cannot be looked at cannot be released on the
  audit's word. Text-like files (``.md``, ``.txt``, ``.csv``, ``.xml``, no extension such as
  ``SHA256SUMS``) get the text rule.

Which folder: ``"clean"`` / ``"raw"`` are lake zones; any other name given with a lake is a
release name, checked like ``release verify`` checks it (never a path: ``../..`` is refused)
and required to exist; without a lake, ``zone`` is a local folder. ``release=NAME`` always
means ``releases/NAME``, even for a release called ``clean``.
"""

from v2xlake.audit.report import AuditConfig, AuditError, AuditReport, Finding
from v2xlake.audit.run import audit

__all__ = ["AuditConfig", "AuditError", "AuditReport", "Finding", "audit"]
