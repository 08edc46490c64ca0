"""MJCF builder: a table, a square bin, a mocap plate pusher, and N pieces of one or two kinds.

Collision bits (MuJoCo collides a pair when ``contype_a & conaffinity_b or contype_b & conaffinity_a``):
table 1, pieces 2, walls and plate 4. Pieces take 2|4 (+1 for the table with free joints); the table, walls and plate
take nothing, so static geoms never collide with each other. Geom groups: 0 table, 1 pieces, 2 walls, 3 plate.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from dynres_jax.config import GEOMS, KINDS, SceneConfig

GRAVITY = 9.81
ROOM = 0.5  # the most of the bin's floor the pieces' footprints may cover
GROUP_TABLE, GROUP_PIECES, GROUP_WALLS, GROUP_PLATE = 0, 1, 2, 3


@dataclass(frozen=True, eq=False)
class Scene:
    """A built scene: the MJCF, the compiled MuJoCo model and static per-piece tables (NumPy, length N).

    kind: index into ``config.kinds``; geom_type: index into ``GEOMS``; size: [N, 3] geom half-sizes (unused
    entries 0); rest_height: z of a piece's centre lying on the table; qpos_adr: first qpos of each piece;
    has_yaw: planar pieces with a yaw joint (qpos_adr + 2);
    geom_id: each piece's geom in ``model``.
    """

    config: SceneConfig
    xml: str
    model: mujoco.MjModel
    kind: np.ndarray
    geom_type: np.ndarray
    size: np.ndarray
    rest_height: np.ndarray
    rgb: np.ndarray
    qpos_adr: np.ndarray
    has_yaw: np.ndarray
    geom_id: np.ndarray
    plate_mocap: int

    @property
    def n_pieces(self) -> int:
        return len(self.kind)

    @property
    def footprint(self) -> np.ndarray:
        """[N] radius of the disc that holds each piece seen from above (metres)."""
        return _footprint(self.geom_type, self.size)


def _footprint(geom_type: np.ndarray, size: np.ndarray) -> np.ndarray:
    return np.select([geom_type == 0, geom_type == 1], [size[:, 0], size[:, 0] + size[:, 1]],
                     np.hypot(size[:, 0], size[:, 1]))


def check_room(cfg: SceneConfig) -> None:
    """ValueError when the pieces' footprints cover more than ROOM of the bin's floor (no pile of them could settle),
    from the config alone: checked before any scene is built."""
    area, floor = float(np.sum(np.pi * footprint(cfg) ** 2)), (2 * cfg.bin_half_width) ** 2
    if area > ROOM * floor:
        largest = int(sum(cfg.pieces) * ROOM * floor / area)
        raise ValueError(f"{sum(cfg.pieces)} {'/'.join(cfg.kinds)} pieces cover {area / floor:.0%} of the bin's floor "
                         f"(at most {ROOM:.0%}: about {largest} pieces)")


def footprint(cfg: SceneConfig) -> np.ndarray:
    """``Scene.footprint`` of the scene ``cfg`` would build, without building it (no MJCF, no compile): [N] m."""
    _, geom_type, size = _piece_sizes(cfg)
    return _footprint(geom_type, size)


def _piece_sizes(cfg: SceneConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-piece kind index, geom type and [N, 3] half-sizes, with each kind's size spread drawn once."""
    rng = np.random.default_rng(cfg.size_seed)
    kind, gtype, size = [], [], []
    for i, (name, n) in enumerate(zip(cfg.kinds, cfg.pieces, strict=True)):
        k = KINDS[name]
        s = np.zeros((n, 3))
        s[:, : len(k.size)] = k.size
        s *= 1.0 + k.size_spread * rng.uniform(-1.0, 1.0, size=(n, 1))
        kind += [i] * n
        gtype += [GEOMS.index(k.geom)] * n
        size.append(s)
    return np.array(kind), np.array(gtype), np.concatenate(size)


def _fmt(v) -> str:
    return " ".join(f"{x:.6g}" for x in np.atleast_1d(v))


def _piece_xml(i: int, name: str, gtype: int, size: np.ndarray, rest: float, cfg: SceneConfig) -> str:
    k = KINDS[name]
    geom = GEOMS[gtype]
    gsize = _fmt(size[: len(k.size)])
    orient = ' euler="0 90 0"' if geom == "capsule" else ""  # capsules lie along the body's x axis
    planar = cfg.joints == "planar"
    conaff = 6 if planar else 7
    rgba = _fmt((*k.rgb, 1.0))
    geom_xml = (f'<geom name="piece{i}" type="{geom}" size="{gsize}"{orient} mass="{k.mass:.6g}" '
                f'friction="{k.friction:.6g} 0.005 0.0001" contype="2" conaffinity="{conaff}" '
                f'group="{GROUP_PIECES}" rgba="{rgba}"/>')
    if planar:
        # Table friction as dry friction on the sliding joints: mu * m * g (N), and on the yaw hinge times a lever
        # arm of half the footprint (N m). No table contact: the piece stays at its rest height.
        f_slide = k.friction * k.rolling_planar * k.mass * GRAVITY
        f_yaw = f_slide * 0.5 * float(size[0] + (size[1] if geom == "capsule" else 0.0))
        joints = (f'<joint name="piece{i}_x" type="slide" axis="1 0 0" frictionloss="{f_slide:.6g}" damping="1e-4"/>'
                  f'<joint name="piece{i}_y" type="slide" axis="0 1 0" frictionloss="{f_slide:.6g}" damping="1e-4"/>')
        if geom != "sphere" or cfg.sphere_yaw:  # a sphere's yaw is invisible: without it, a third fewer dofs
            joints += (f'<joint name="piece{i}_yaw" type="hinge" axis="0 0 1" frictionloss="{f_yaw:.6g}" '
                       f'damping="1e-7" armature="1e-7"/>')
    else:
        joints = f'<freejoint name="piece{i}"/>' if k.rolling <= 0 else \
            f'<joint name="piece{i}" type="free" damping="{k.rolling:.6g}"/>'
    return f'<body name="body{i}" pos="0 0 {rest:.6g}">{joints}{geom_xml}</body>'


def scene_xml(cfg: SceneConfig) -> str:
    """The MJCF text of a scene (pieces start at the origin; ``PileEnv.reset`` places them)."""
    kind, gtype, size = _piece_sizes(cfg)
    n = len(kind)
    rest = np.where(gtype == 2, size[:, 2], size[:, 0])
    b, t, h = cfg.bin_half_width, cfg.wall_thickness, cfg.wall_height
    walls = []  # collision planes facing into the bin (MJX culls no plane pairs); the camera draws them as boxes
    for j, (x, y, axis) in enumerate([(b, 0, "-1 0 0"), (-b, 0, "1 0 0"), (0, b, "0 -1 0"), (0, -b, "0 1 0")]):
        walls.append(f'<geom name="wall{j}" type="plane" pos="{x:.6g} {y:.6g} {h / 2:.6g}" zaxis="{axis}" '
                     f'size="{h / 2:.6g} {b + t:.6g} 0.01" contype="4" conaffinity="0" group="{GROUP_WALLS}" '
                     f'friction="0.1" rgba="0.6 0.6 0.6 1"/>')
    pieces = "\n    ".join(_piece_xml(i, cfg.kinds[kind[i]], gtype[i], size[i], rest[i], cfg) for i in range(n))
    cap = max(1, int(round(cfg.contact_cap * n)))
    if cfg.plate_geom == "capsule":  # a rod along the body's y axis, perpendicular to the push
        plate = f'type="capsule" size="{cfg.plate_thickness / 2:.6g} {cfg.plate_half_width:.6g}" euler="90 0 0"'
    else:
        plate = (f'type="box" size="{cfg.plate_thickness / 2:.6g} {cfg.plate_half_width:.6g} '
                 f'{cfg.plate_half_height:.6g}"')
    return f"""<mujoco model="pile">
  <option timestep="{cfg.timestep:.6g}" iterations="{cfg.solver_iterations}" ls_iterations="{cfg.ls_iterations}"
          solver="{cfg.solver}" cone="{cfg.cone}"/>
  <custom>
    <numeric name="max_contact_points" data="{cap}"/>
    <numeric name="max_geom_pairs" data="{cap}"/>
  </custom>
  <default><geom solref="{cfg.solref:.6g} 1" condim="{cfg.condim}"/></default>
  <worldbody>
    <geom name="table" type="plane" size="{b + 0.1:.6g} {b + 0.1:.6g} 0.01" contype="1" conaffinity="0"
          group="{GROUP_TABLE}" friction="0.1" rgba="0.9 0.9 0.88 1"/>
    {"".join(walls)}
    <body name="pusher" mocap="true" pos="0 0 1">
      <geom name="plate" {plate} contype="4" conaffinity="0" group="{GROUP_PLATE}" friction="0.3"
            rgba="0.2 0.2 0.2 1"/>
    </body>
    {pieces}
  </worldbody>
</mujoco>
"""


def build_scene(cfg: SceneConfig) -> Scene:
    """Build the MJCF for ``cfg`` and compile it with MuJoCo. Raises ValueError naming any bad field, or a pile with
    no room in the bin (``check_room``)."""
    check_room(cfg)
    xml = scene_xml(cfg)
    model = mujoco.MjModel.from_xml_string(xml)
    kind, gtype, size = _piece_sizes(cfg)
    n = len(kind)
    rest = np.where(gtype == 2, size[:, 2], size[:, 0])
    rgb = np.array([KINDS[cfg.kinds[k]].rgb for k in kind])
    joint0 = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT,
                                         f"piece{i}_x" if cfg.joints == "planar" else f"piece{i}") for i in range(n)])
    geom_id = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"piece{i}") for i in range(n)])
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "pusher")
    has_yaw = (gtype != 0) | cfg.sphere_yaw if cfg.joints == "planar" else np.zeros(n, bool)
    return Scene(cfg, xml, model, kind, gtype, size, rest, rgb, model.jnt_qposadr[joint0], has_yaw, geom_id,
                 int(model.body_mocapid[body]))
