"""Configuration: frozen dataclasses with documented defaults, one place for units and bounds.

Units: metres, kilograms, seconds, radians. World frame: z up, table top at z = 0, the workspace a square bin
centred at the origin. Every field can be overridden by name (``dataclasses.replace`` or a CLI flag).
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
from dataclasses import dataclass, field

GEOMS = ("sphere", "capsule", "box")
OMEGA_MIN, OMEGA_MAX = 2, 100  # the resolutions ω a planner may use (the reference's search range); the one place


def check_omega(omega, what: str = "omega") -> int:
    """ω as an int in [OMEGA_MIN, OMEGA_MAX], or a ValueError naming ``what``."""
    if isinstance(omega, bool) or int(omega) != omega or not OMEGA_MIN <= omega <= OMEGA_MAX:
        raise ValueError(f"{what} must be an integer in [{OMEGA_MIN}, {OMEGA_MAX}], got {omega!r}")
    return int(omega)


def check_fields(cfg) -> None:
    """Check a config dataclass's fields against their annotations: TypeError naming the field when an ``int``,
    ``float``, ``bool`` or ``str`` field, or an element of a ``tuple[T, ...]`` of them, holds another type (a float
    takes whole numbers; a number is never a bool; a tuple is not a string), ValueError for a number that is not
    finite. Other annotations (nested configs) are left to the class."""
    for f in dataclasses.fields(cfg):
        value, kind = getattr(cfg, f.name), str(f.type)
        if kind.endswith(" | None"):
            if value is None:
                continue
            kind = kind.removesuffix(" | None")
        where = f"{type(cfg).__name__}.{f.name}"
        if kind.startswith("tuple[") and kind.endswith(", ...]") and kind[6:-6] in ("int", "float", "bool", "str"):
            if isinstance(value, str | bytes) or not isinstance(value, tuple | list):
                raise TypeError(f"{where} must be a tuple of {kind[6:-6]}s, got {value!r}")
            for i, item in enumerate(value):
                _check_value(f"{where}[{i}]", kind[6:-6], item)
        else:
            _check_value(where, kind, value)


def _check_value(where: str, kind: str, value) -> None:
    """``check_fields``' rule for one value annotated ``kind`` ("int", "float", "bool", "str"; others pass)."""
    numeric = isinstance(value, numbers.Real) and not isinstance(value, bool)
    ok = {"int": numeric and isinstance(value, numbers.Integral), "float": numeric,
          "bool": isinstance(value, bool) or type(value).__name__ == "bool_", "str": isinstance(value, str)}
    if kind not in ok:
        return
    if not ok[kind]:
        raise TypeError(f"{where} must be {'an' if kind == 'int' else 'a'} {kind}, got {value!r}")
    if kind == "float" and not math.isfinite(value):
        raise ValueError(f"{where} must be a finite number, got {value!r}")


@dataclass(frozen=True)
class PieceKind:
    """One kind of object in a pile.

    geom: MuJoCo primitive ("sphere", "capsule" lying flat, "box" lying flat).
    size: sphere (radius,), capsule (radius, half_length of the cylinder part), box (hx, hy, hz) half-sizes, metres.
    size_spread: relative spread of every size, drawn per piece once when the scene is built (granola: mixed sizes).
    mass: kilograms per piece.  friction: sliding friction coefficient against the table, other pieces and walls.
    rolling: rolling resistance. Free joints: rotational damping (N·m·s/rad); planar joints: the table's dry friction
      is multiplied by ``rolling_planar`` instead (M&M roll, so they coast further).
    rgb: colour in [0, 1], used by the renderer.
    """

    name: str
    geom: str
    size: tuple[float, ...]
    mass: float
    friction: float
    rolling: float
    rgb: tuple[float, float, float]
    size_spread: float = 0.0
    rolling_planar: float = 1.0

    def __post_init__(self):
        if self.geom not in GEOMS:
            raise ValueError(f"piece kind {self.name!r}: geom {self.geom!r} is not one of {GEOMS}")
        expected = {"sphere": 1, "capsule": 2, "box": 3}[self.geom]
        if len(self.size) != expected or min(self.size) <= 0:
            raise ValueError(f"piece kind {self.name!r}: a {self.geom} needs {expected} positive sizes, "
                             f"got {self.size}")


# The paper's object variety (its Fig. 3b and 6c): round, elongated, rolling, irregular and large square pieces.
KINDS: dict[str, PieceKind] = {
    k.name: k
    for k in (
        PieceKind("coffee", "sphere", (0.007,), 0.002, 0.5, 1e-5, (0.36, 0.22, 0.12)),
        PieceKind("almond", "capsule", (0.006, 0.008), 0.003, 0.5, 1e-5, (0.76, 0.55, 0.36)),
        PieceKind("rice", "capsule", (0.004, 0.006), 0.001, 0.6, 1e-5, (0.93, 0.91, 0.84)),
        PieceKind("mnm", "sphere", (0.0075,), 0.002, 0.3, 1e-7, (0.85, 0.15, 0.15), rolling_planar=0.3),
        PieceKind("granola", "sphere", (0.008,), 0.002, 0.7, 1e-4, (0.80, 0.65, 0.35), size_spread=0.35),
        PieceKind("candy", "box", (0.011, 0.011, 0.006), 0.005, 0.6, 1e-5, (0.20, 0.45, 0.85)),
    )
}


def check_kind_names(kinds, field: str) -> None:
    """A ValueError naming ``field`` and the entries of ``kinds`` that are not piece kinds (``KINDS``)."""
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise ValueError(f"{field}: unknown piece kind(s) {unknown}; known: {', '.join(KINDS)}")


# Pieces per kind for piles of comparable area (the paper's piles): 100 coffee beans' footprint (the discs that hold
# the pieces seen from above), about 0.015 m², in every kind (tests/test_tasks.py checks it on the built scenes).
DEFAULT_PIECES: dict[str, int] = {"coffee": 100, "almond": 25, "rice": 49, "mnm": 87, "granola": 69, "candy": 20}


MAX_PIECES = 10_000  # pieces of one kind at most (a 0.4 m bin holds a few hundred): past it, a count is a typo


@dataclass(frozen=True)
class SceneConfig:
    """What is on the table and how MuJoCo simulates it.

    kinds / pieces: piece kind names and how many of each (two kinds for Sort). joints: "planar" pieces slide on the
    table (x, y, yaw; table friction as joint dry friction, no table contacts: 3 degrees of freedom a piece, the fast
    choice) or "free" (6 degrees of freedom, real table contacts, pieces can tip and stack).
    sphere_yaw: planar spheres get a yaw joint too (invisible for a sphere; off: 2 degrees of freedom, faster).
    contact_cap: MJX keeps at most ``contact_cap * n_pieces`` contacts and candidate pairs per group. A packed pile
      of discs has about 2 touching pairs a piece, plus walls and plate; fewer let pieces pass into each other.
    cone: friction cone, "pyramidal" (4 constraint rows a contact) or "elliptic" (3).
    condim: contact dimension of pieces, walls and plate: 3 (with friction) or 1 (frictionless: one constraint row
      a contact, so MJX's dense solver reads a quarter of the rows; the table's friction on the joints stays).
    solver: "Newton" or "CG". Under MJX (float32) CG let piles of almonds, candies and M&M diverge within a push
      (1,000 random pushes each on an H100: 35-99 % broken) where C MuJoCo with the same model did not; with
      frictionless contacts (condim 1) only candy (boxes) still does.
    ``SceneConfig.fast(...)`` is the scene MJX simulates fastest that still passes the physics checks.
    plate_geom: "capsule" (default: a rod of diameter ``plate_thickness`` and length ``2 plate_half_width``
      perpendicular to the push, its axis at the pieces' height) or "box" (a plate ``plate_half_height`` tall). MJX
      turned box and capsule pieces to NaN against the box plate (H100 and CPU, MuJoCo 3.17); the rod collides
      through MJX's sphere/capsule primitives and looks the same from above.
    """

    kinds: tuple[str, ...] = ("coffee",)
    pieces: tuple[int, ...] = (100,)
    joints: str = "planar"
    bin_half_width: float = 0.2
    wall_height: float = 0.04
    wall_thickness: float = 0.01
    plate_half_width: float = 0.04
    plate_thickness: float = 0.01
    plate_half_height: float = 0.02
    plate_geom: str = "capsule"
    timestep: float = 0.002
    solver_iterations: int = 12
    ls_iterations: int = 6
    solref: float = 0.005
    contact_cap: float = 3.0
    sphere_yaw: bool = False
    cone: str = "pyramidal"
    condim: int = 3
    solver: str = "Newton"
    size_seed: int = 0

    def __post_init__(self):
        check_fields(self)
        if len(self.kinds) != len(self.pieces) or not self.kinds:
            raise ValueError(f"kinds {self.kinds} and pieces {self.pieces} must be non-empty and of equal length")
        for k in self.kinds:
            if k not in KINDS:
                raise ValueError(f"unknown piece kind {k!r}; known kinds: {sorted(KINDS)}")
        if min(self.pieces) < 1 or max(self.pieces) > MAX_PIECES:
            raise ValueError(f"every kind needs between 1 and {MAX_PIECES} pieces, got pieces={self.pieces}")
        if self.plate_geom not in ("capsule", "box"):
            raise ValueError(f"plate_geom must be 'capsule' or 'box', got {self.plate_geom!r}")
        if self.solver not in ("CG", "Newton"):
            raise ValueError(f"solver must be 'CG' or 'Newton', got {self.solver!r}")
        if self.cone not in ("pyramidal", "elliptic"):
            raise ValueError(f"cone must be 'pyramidal' or 'elliptic', got {self.cone!r}")
        if self.condim not in (1, 3):
            raise ValueError(f"condim must be 1 or 3, got {self.condim!r}")
        if self.joints not in ("planar", "free"):
            raise ValueError(f"joints must be 'planar' or 'free', got {self.joints!r}")

    @property
    def n_pieces(self) -> int:
        return sum(self.pieces)

    @classmethod
    def fast(cls, kinds: tuple[str, ...] = ("coffee",), pieces: tuple[int, ...] = (100,), **overrides) -> SceneConfig:
        """The fast scene for batched MJX: frictionless contacts (condim 1), caps 2N, CG with at most 8 iterations
        of 3 line-search steps; Newton for scenes with boxes (CG let candy piles diverge). docs/performance.md,
        "Speed": over 2x C MuJoCo on all 16 cores of an H200 host at 100 coffee beans (the default scene: 0.2x), and
        its physics checks."""
        return cls(kinds=kinds, pieces=pieces, **{**fast_fields(kinds), **overrides})


def fast_fields(kinds: tuple[str, ...]) -> dict:
    """The SceneConfig fields that make ``SceneConfig.fast``'s physics for these kinds (the rest stay as given)."""
    boxes = any(KINDS[k].geom == "box" for k in kinds if k in KINDS)
    solver = dict(solver="Newton") if boxes else dict(solver="CG", solver_iterations=8)
    return dict(condim=1, contact_cap=2.0, ls_iterations=3, **solver)


@dataclass(frozen=True)
class PushConfig:
    """One push: the plate lowers at the start, moves at constant ``speed`` along the line, lifts, the pile settles.

    The move phase lasts ``max_length / speed`` seconds for every push (the plate waits at the end of a shorter one),
    so a push is a fixed number of simulator steps and batches without padding.
    """

    speed: float = 0.25
    max_length: float = 0.25
    min_length: float = 0.01
    lower_time: float = 0.04
    lift_time: float = 0.04
    settle_time: float = 0.1
    clearance: float = 0.002
    lift_height: float = 0.08

    def __post_init__(self):
        check_fields(self)


@dataclass(frozen=True)
class PileConfig:
    """Initial piles. layout: "blob" (one pile), "two_blobs" (two piles; with two kinds, one kind each),
    "spread" (uniform over the bin). blob_radius bounds the pile centres' distance from the bin centre."""

    layout: str = "blob"
    centre_margin: float = 0.06
    jitter: float = 0.4
    settle_time: float = 0.2

    def __post_init__(self):
        check_fields(self)
        if self.layout not in ("blob", "two_blobs", "spread"):
            raise ValueError(f"pile layout must be 'blob', 'two_blobs' or 'spread', got {self.layout!r}")


@dataclass(frozen=True)
class CameraConfig:
    """Top-down pinhole camera above the bin centre, looking down; image rows run along -y, columns along +x.

    view_half_width: half the side of the square the image covers on the table plane (metres).
    """

    width: int = 128
    height: int = 128
    distance: float = 1.0
    view_half_width: float = 0.23

    def __post_init__(self):
        check_fields(self)


@dataclass(frozen=True)
class SimConfig:
    scene: SceneConfig = field(default_factory=SceneConfig)
    push: PushConfig = field(default_factory=PushConfig)
    pile: PileConfig = field(default_factory=PileConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @staticmethod
    def from_json(text: str) -> SimConfig:
        """Inverse of ``to_json`` (lists back to tuples)."""
        d = json.loads(text)
        fix = lambda sub: {k: tuple(v) if isinstance(v, list) else v for k, v in sub.items()}  # noqa: E731
        return SimConfig(scene=SceneConfig(**fix(d["scene"])), push=PushConfig(**fix(d["push"])),
                         pile=PileConfig(**fix(d["pile"])), camera=CameraConfig(**fix(d["camera"])))


def replace(cfg, **overrides):
    """``dataclasses.replace`` that names the field when it does not exist."""
    names = {f.name for f in dataclasses.fields(cfg)}
    unknown = set(overrides) - names
    if unknown:
        raise ValueError(f"{type(cfg).__name__} has no field(s) {sorted(unknown)}; fields: {sorted(names)}")
    return dataclasses.replace(cfg, **overrides)
