"""Cameras built around a Gaussian scene that comes without its capture cameras.

:func:`orbit_cameras` places views on rings around the scene's centre (roll-free, all
looking at it; the centre, subject radius and up of :func:`~artnvg_core.cameras.scene_frame`),
at the distance where the subject sphere fills the field of view: all round, or for a
one-sided (forward-facing) capture on the arc the capture looked from (:func:`captured_arc`:
probe views find the side from which floaters and the background the cameras saw do not hide
the subject), pulled in where the views would stand inside the background around the subject
(:func:`pulled_in`). The probes render, so this module sits above :mod:`artnvg_core.raster`, outside
:mod:`artnvg_core.cameras`. World units and axes are the scene's; cameras follow the OpenCV
convention of :mod:`artnvg_core.cameras`. All pose maths runs in float64 on the CPU; the probes
render in float32. :func:`parse_elevations` reads the rings' elevations from text (the node's input).
"""

from __future__ import annotations

import logging
import math

import torch

from .cameras import CameraSet, SceneFrame, look_at, scene_frame
from .cameras.camera_set import view_count, whole_number
from .cameras.framing import horizontal_axes
from .notes import NoteFn, tell
from .raster import render
from .scene import GaussianScene

_log = logging.getLogger(__name__)

AROUND = ("auto", "full")
_PROBE_AZIMUTHS = 24  # probe views per ring when looking for the side the capture saw
_PROBE_PIXELS = 24  # their size, square
_BLOCKED = 0.75  # a probe view with more of it covered by foreground than this is blocked
_MIN_GAP_DEG = 90.0  # blocked azimuths spanning at least this: a one-sided capture
_PULL = 0.85  # each pull moves the views in to this fraction of their distance from the centre
_CLOSEST = 0.6  # ... down to no less than this fraction


def parse_elevations(elevations, what: str | None = None) -> list[float]:
    """Ring elevations in degrees from ``elevations``: numbers, or comma-separated text of them ("10, 30", the
    node's elevations input); at least one, each in (-90, 90).

    Raises ValueError naming the offending entry, after ``what:`` (a field's name) when given.
    """
    where = f"{what}: " if what else ""
    parts = [part for part in elevations.split(",") if part.strip()] if isinstance(elevations, str) else elevations
    angles = []
    for part in parts:
        try:
            angle = float(part)
        except (TypeError, ValueError):
            raise ValueError(f"{where}expected comma-separated angles in degrees such as 10, 30, got {part!r} "
                             f"in {elevations!r}") from None
        if not -90 < angle < 90:
            raise ValueError(f"{where}{angle:g} degrees is not an elevation in (-90, 90), in {elevations!r}")
        angles.append(angle)
    if not angles:
        raise ValueError(f"{where}expected at least one angle in degrees, got {elevations!r}")
    return angles


def _ring_counts(count: int, elevations: list[float]) -> list[int]:
    """Views per ring, proportional to each ring's circumference (largest remainders)."""
    shares = torch.tensor([math.cos(math.radians(e)) for e in elevations], dtype=torch.float64)
    exact = count * shares / shares.sum()
    counts = exact.floor().long()
    for i in torch.argsort(exact - counts, descending=True)[: count - int(counts.sum())]:
        counts[i] += 1
    return counts.tolist()


def _eyes(frame: SceneFrame, distance: float, azimuths: torch.Tensor, elevation_deg: float) -> torch.Tensor:
    """Camera centres [A, 3] at ``distance`` from the centre, at ``azimuths`` [A] (radians about
    up, from :func:`horizontal_axes`' first axis towards its second) and one elevation in degrees."""
    side, front = horizontal_axes(frame.up)
    horizontal = torch.cos(azimuths)[:, None] * side + torch.sin(azimuths)[:, None] * front
    lift = math.radians(elevation_deg)
    return frame.center + distance * (math.cos(lift) * horizontal + math.sin(lift) * frame.up)


def occluded_fractions(scene: GaussianScene, frame: SceneFrame, eyes: torch.Tensor, half_fov: float) -> torch.Tensor:
    """Fraction [V] of each probe view covered by what lies in front of the subject sphere.

    eyes: [V, 3] float64 camera centres looking at ``frame.center`` with half field of view
    ``half_fov`` (radians). Only the Gaussians whose depth along the view axis is positive and
    short of the subject sphere are rendered (the reference rasterizer, float32 on the CPU,
    :data:`_PROBE_PIXELS` square, SH degree 0); the fraction is their mean alpha.
    """
    means = scene.means.detach().cpu().to(torch.float64)
    world_to_cam = look_at(eyes, frame.center, frame.up).to(torch.float32)
    focal = _PROBE_PIXELS / 2 / math.tan(half_fov)
    intrinsics = torch.tensor([[[focal, 0, _PROBE_PIXELS / 2], [0, focal, _PROBE_PIXELS / 2], [0, 0, 1]]])
    fractions = torch.zeros(len(eyes), dtype=torch.float64)
    for view, eye in enumerate(eyes):
        axis = frame.center - eye
        depth = (means - eye) @ (axis / axis.norm())
        front = torch.nonzero((depth > 0) & (depth < axis.norm() - frame.radius)).flatten()
        if len(front) == 0:
            continue
        probe = CameraSet(world_to_cam[view : view + 1], intrinsics, _PROBE_PIXELS, _PROBE_PIXELS, ["probe"])
        occluders = scene.select(front.to(scene.device)).detach().to("cpu", torch.float32)
        with torch.no_grad():
            fractions[view] = render(occluders, probe, sh_degree=0, backend="torch").alpha.mean().double()
    return fractions


def captured_arc(scene: GaussianScene, frame: SceneFrame, distance: float, half_fov: float,
                 elevations_deg: list[float]) -> tuple[float, float]:
    """(start, span) in radians of the azimuths the capture looked from (:func:`_eyes`' convention);
    span is 2 pi for a capture all round.

    A capture camera sees its subject unobstructed, so 3DGS training leaves the space between
    them empty; seen from where no camera stood, the subject hides behind floaters and behind
    what the cameras saw beyond it (a portrait's wall). Probe views at ``distance`` on every
    ring of ``elevations_deg``, every 360 / :data:`_PROBE_AZIMUTHS` degrees, measure
    :func:`occluded_fractions`; an azimuth whose mean over the rings exceeds :data:`_BLOCKED`
    is blocked. When the longest run of blocked azimuths spans at least :data:`_MIN_GAP_DEG`
    degrees the capture was one-sided: the cameras stood about opposite the background they saw
    behind the subject, and each saw it across its field of view, so the run is about the
    capture's arc mirrored through the centre and widened by a field of view. The arc is centred
    opposite the run's middle, as wide as the run (no wider than the clear rest of the circle)
    less ``2 * half_fov`` (the probe's, standing in for the capture's unknown one), but at least
    half that width. Otherwise (the scattered bushes and trees of a 360-degree capture) it is the
    whole circle.
    """
    step = 2 * math.pi / _PROBE_AZIMUTHS
    azimuths = torch.arange(_PROBE_AZIMUTHS, dtype=torch.float64) * step
    eyes = torch.cat([_eyes(frame, distance, azimuths, elevation) for elevation in elevations_deg])
    fractions = occluded_fractions(scene, frame, eyes, half_fov).view(len(elevations_deg), -1).mean(0)
    blocked = (fractions > _BLOCKED).tolist()
    if all(blocked):
        _log.warning("every view around the scene looks through foreground (%.0f %% of it covered on average); "
                     "orbiting all round", 100 * float(fractions.mean()))
    if all(blocked) or not any(blocked):
        return 0.0, 2 * math.pi
    first_clear = blocked.index(False)
    longest, run, gap_start = 0, 0, 0
    for k in range(first_clear + 1, first_clear + 1 + _PROBE_AZIMUTHS):  # circularly, from a clear azimuth
        run = run + 1 if blocked[k % _PROBE_AZIMUTHS] else 0
        if run > longest:
            longest, gap_start = run, k - run + 1
    if longest * step < math.radians(_MIN_GAP_DEG):
        return 0.0, 2 * math.pi
    mirrored = min(longest, _PROBE_AZIMUTHS - longest) * step
    span = max(mirrored - 2 * half_fov, mirrored / 2)
    axis = (gap_start + (longest - 1) / 2) * step + math.pi  # opposite the blocked run's middle
    _log.info("a one-sided capture: from %.0f degrees of azimuth the subject is %.0f %% hidden by floaters or "
              "background; the views stay on a %.0f-degree arc opposite", math.degrees(longest * step),
              100 * float(fractions[blocked].mean()), math.degrees(span))
    return float(axis - span / 2), span


def pulled_in(scene: GaussianScene, frame: SceneFrame, eyes: torch.Tensor, half_fov: float) -> torch.Tensor:
    """``eyes`` [V, 3] (float64, looking at ``frame.center``) moved towards the centre, all by one factor, until none
    is blocked (:func:`occluded_fractions` over :data:`_BLOCKED`).

    The subject-filling distance can stand beyond where the capture cameras stood, inside the bushes and trees
    around the subject, which training fills wherever no camera needed the space empty: on the shared bear
    and garden 2 and 10 of 60 views were over 75 % covered (at 2.0 and 1.6 times the capture's median distance).
    Each pull takes the distance to :data:`_PULL` of itself, down to no less than :data:`_CLOSEST` of the
    starting one: outside the subject sphere still, where the capture cameras stood (bear: 0.72, garden: 0.61).
    """
    offsets = eyes - frame.center
    pull = 1.0
    while pull * _PULL >= _CLOSEST and bool(
            (occluded_fractions(scene, frame, frame.center + pull * offsets, half_fov) > _BLOCKED).any()):
        pull *= _PULL
    if pull < 1:
        _log.info("views pulled in to %.0f %% of the subject-filling distance, out of the scene's background",
                  100 * pull)
    return frame.center + pull * offsets


def orbit_view_names(count: int) -> list[str]:
    """The names of the ``count`` views :func:`orbit_cameras` builds: ``orbit_0000``, ``orbit_0001``..."""
    return [f"orbit_{i:04d}" for i in range(count)]


def orbit_cameras(
    scene: GaussianScene,
    count: int = 60,
    *,
    fov_deg: float = 50.0,
    width: int = 512,
    height: int = 512,
    up=None,
    elevations_deg=(10.0, 30.0),
    quantile: float = 0.5,
    distance_factor: float = 1.0,
    around: str = "auto",
    notes: NoteFn | None = None,
    up_option: str = "up='-y'",
) -> CameraSet:
    """``count`` views around ``scene`` on rings about its up axis, all looking at its centre.

    count: number of views (e.g. 60: four neighbouring-view groups of 15).
    fov_deg: horizontal field of view in degrees, in (0, 180); square pixels, so the
        vertical one follows from ``height / width``; principal point at the image centre.
    width, height: image size in pixels.
    up: "auto" / None (detected), an axis name such as "-y" (:data:`UP_AXES`) or a
        3-vector (:func:`~artnvg_core.cameras.parse_up`): the world direction that appears up in every view.
    elevations_deg: one ring per angle above the horizontal plane through the centre,
        each in (-90, 90), as :func:`parse_elevations` takes them; views are shared out by ring circumference, each ring evenly
        spaced in azimuth and offset by half a step from the previous ring.
    quantile: weight fraction of the subject sphere (:func:`scene_frame`).
    distance_factor: the cameras sit ``distance_factor * radius / sin(half fov)`` from
        the centre (the smaller of the horizontal and vertical half angles), so at 1
        the subject sphere just fills the view; above 1 it shows more surroundings; views that
        would stand inside the scene's background there are pulled in (:func:`pulled_in`).
    around: "auto" puts the rings on the side the capture looked from
        (:func:`captured_arc`: all round for a 360-degree capture, an arc for a
        forward-facing one); "full" always orbits all round.
    notes: where a note goes when ``up`` is a guess (:func:`scene_frame`'s "long axis"; no ground
        found), as :mod:`artnvg_core.notes` tells it: a node's text, a command's printed lines.
    up_option: how the caller's user sets ``up``, with an example, for that note: "--up=-y" on
        the command line, the up input of a node.
    Views are named ``orbit_0000``...; float32 CPU tensors.
    """
    count = view_count(count, "orbit_cameras: count")
    if not 0 < fov_deg < 180:
        raise ValueError(f"orbit_cameras: fov_deg must be in (0, 180), got {fov_deg!r}")
    if not (distance_factor > 0 and math.isfinite(distance_factor)):
        raise ValueError(f"orbit_cameras: distance_factor must be a positive number, got {distance_factor!r}")
    elevations = parse_elevations(elevations_deg, "orbit_cameras: elevations_deg")
    if around not in AROUND:
        raise ValueError(f"orbit_cameras: around must be one of {AROUND}, got {around!r}")
    width, height = whole_number(width, "orbit_cameras: width"), whole_number(height, "orbit_cameras: height")
    if width < 1 or height < 1:
        raise ValueError(f"orbit_cameras: image size must be positive, got {width}x{height}")

    frame = scene_frame(scene, up=up, quantile=quantile)
    if frame.up_source == "long axis":
        tell(notes, "scene", "the up direction is a guess, the long axis of the scene's core (no ground plane found); "
             f"if the views come out tilted or upside down, give the scene's up axis: {up_option}")
    focal = width / 2 / math.tan(math.radians(fov_deg) / 2)
    half_fov = min(math.atan(width / 2 / focal), math.atan(height / 2 / focal))
    distance = distance_factor * frame.radius / math.sin(half_fov)
    start, span = (0.0, 2 * math.pi) if around == "full" else captured_arc(scene, frame, distance, half_fov, elevations)

    eyes = []
    for ring, (elevation, views) in enumerate(zip(elevations, _ring_counts(count, elevations))):
        steps = torch.arange(views, dtype=torch.float64)
        if span < 2 * math.pi:  # an arc: each ring spread over it, half a step in from its ends
            azimuths = start + (steps + 0.5) * (span / max(views, 1))
        else:  # all round: each ring offset by half a step from the previous one
            azimuths = start + (steps + 0.5 * (ring % 2)) * (span / max(views, 1))
        eyes.append(_eyes(frame, distance, azimuths, elevation))
    world_to_cam = look_at(pulled_in(scene, frame, torch.cat(eyes), half_fov), frame.center, frame.up)
    intrinsics = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float64)
    return CameraSet(
        world_to_cam=world_to_cam.to(torch.float32),
        intrinsics=intrinsics.expand(count, 3, 3).to(torch.float32).clone(),
        width=width,
        height=height,
        names=orbit_view_names(count),
    )
