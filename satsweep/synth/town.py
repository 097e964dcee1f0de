"""The synthetic surface of ``satsweep synth``: a seeded town on a fine height grid, ray casting
through it, sun shadows and Lambertian shading.

The surface is a *piecewise-planar height field* on a regular grid of square cells (``cell_m``,
0.25 m by default) in a local ENU frame (metres; ``u`` is up): inside cell (j, i) the height is
the plane ``top[j, i] + slope_e[j, i] * (e - e_c) + slope_n[j, i] * (n - n_c)`` about the cell
centre (e_c, n_c). Where neighbouring planes disagree the surface has a vertical wall on the
shared cell edge. So flat and gabled roofs are exact planes, walls are exactly vertical, and
gentle ground is planar per cell (its steps between cells are micrometres). This field *is* the
ground truth: the renderer intersects lines of sight with it exactly (no sampling along the
ray), and the truth DSM is its maximum per DSM cell.

Row ``j`` of every grid array runs along north (j = 0 is the southern row), column ``i`` along
east; cell (j, i) covers ``e_min + [i, i + 1) * cell_m`` by ``n_min + [j, j + 1) * cell_m``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

# Materials of the top surface of a cell.
GROUND = 0  # grass and soil
ROAD = 1  # asphalt with lane markings
SIDEWALK = 2  # paving slabs
PLAZA = 3  # plain paving: weakly textured
ROOF = 4  # flat roof: mostly plain (weakly textured), some gravel
ROOF_GABLE = 5  # tiled gabled roof
ROOF_BOX = 6  # small structure on a flat roof (stair house, air conditioning)
TREE = 7  # tree crown
# Materials that only the images of a multi-date scene show (``satsweep.synth.multidate``), never
# the truth surface: transients and the ground seen through a leafless crown.
VEHICLE = 8  # car, van or truck parked or driving on a road
STALL = 9  # market stall or tent on a plaza
MATERIAL_NAMES = ("ground", "road", "sidewalk", "plaza", "roof", "gable_roof", "roof_box", "tree",
                  "vehicle", "stall")

# Heights of buildings (walls to the top of the roof), metres, as the issue specifies.
MIN_BUILDING_M = 4.0
MAX_BUILDING_M = 60.0
# Storey height used for building heights and facade window rows (m).
STOREY_M = 3.1
# Bound on |ground height| over the scene relative to the centre (m): slope and undulation are
# scaled to stay within it, so the altitude range is known before the layout is drawn.
GROUND_RELIEF_M = 4.0
# Tallest tree (m above ground).
MAX_TREE_M = 16.0

# Walls lower than this are cell-to-cell steps of the gently curved ground or of a tree crown's
# flank, not facades: they are shaded as the top surface of the cell.
MIN_WALL_M = 0.02
# Height tolerance of the shadow test (m): a point is in shadow only when an occluder rises more
# than this above the ray towards the sun (absorbs float rounding on sunlit planes).
SHADOW_TOLERANCE_M = 1e-3


@dataclasses.dataclass(frozen=True)
class Building:
    """A rectangular building (ENU metres); the roof top is ``base_u + height_m``."""

    e0: float
    n0: float
    e1: float
    n1: float
    base_u: float  # ground height under the building (max over its corners), ENU up (m)
    height_m: float  # from base_u to the highest roof point
    roof: str  # "flat" or "gable"

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class SurfaceGrid:
    """The piecewise-planar height field (see the module docstring) and its materials."""

    e_min: float  # west edge of the grid (ENU m)
    n_min: float  # south edge of the grid (ENU m)
    cell_m: float  # cell size (m)
    top: np.ndarray  # (ny, nx) float64: plane height at the cell centre (ENU up, m)
    slope_e: np.ndarray  # (ny, nx) float64: dh/de in the cell
    slope_n: np.ndarray  # (ny, nx) float64: dh/dn in the cell
    material: np.ndarray  # (ny, nx) uint8: one of GROUND .. TREE
    albedo: np.ndarray  # (ny, nx) float32: reflectance of the top surface, 0..1
    wall_albedo: np.ndarray  # (ny, nx) float32: reflectance of this cell's walls (facades)
    ground: "GroundShape"  # analytic bare ground, for heights above ground on facades
    buildings: tuple[Building, ...] = ()
    # The street grid: (north-south road eastings, their widths, east-west road northings, their
    # widths), metres; where the multi-date scenes park their cars.
    roads: tuple = ((), (), (), ())
    # The trees: (e, n, crown radius, total height, crown depth, leaf albedo) each, metres.
    trees: tuple[tuple[float, ...], ...] = ()
    # What lies under the tree crowns: the cells (j, i) that a crown covers and their top, slopes,
    # material, albedo and wall albedo before the crowns were drawn (what a leafless crown lets
    # through). None when the grid was not drawn by build_surface.
    under_trees: "UnderTrees | None" = None
    # (ny, nx) float32: how green each tree cell's leaves are on the surface's date (1: leaves
    # in summer, less in autumn, 0: bare branches); None: 1 everywhere (a single-date scene).
    leafiness: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.top.shape

    @property
    def e_max(self) -> float:
        return self.e_min + self.top.shape[1] * self.cell_m

    @property
    def n_max(self) -> float:
        return self.n_min + self.top.shape[0] * self.cell_m

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(e, n) of the cell centres as 1D arrays along i and j."""
        c = self.cell_m
        return (self.e_min + (np.arange(self.top.shape[1]) + 0.5) * c,
                self.n_min + (np.arange(self.top.shape[0]) + 0.5) * c)

    def max_height(self) -> float:
        """Highest point of the surface (the plane maxima at the cell corners)."""
        reach = 0.5 * self.cell_m * (np.abs(self.slope_e) + np.abs(self.slope_n))
        return float(np.max(self.top + reach))

    def min_height(self) -> float:
        """Lowest point of the surface."""
        reach = 0.5 * self.cell_m * (np.abs(self.slope_e) + np.abs(self.slope_n))
        return float(np.min(self.top - reach))

    def cell_of(self, *, e, n) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(j, i, inside) cell indices of points (clipped to the grid) and whether they are in it."""
        e, n = np.broadcast_arrays(np.asarray(e, np.float64), np.asarray(n, np.float64))
        fi = np.floor((e - self.e_min) / self.cell_m)
        fj = np.floor((n - self.n_min) / self.cell_m)
        ny, nx = self.top.shape
        inside = (fi >= 0) & (fi < nx) & (fj >= 0) & (fj < ny)
        i = np.clip(fi, 0, nx - 1).astype(np.int64)
        j = np.clip(fj, 0, ny - 1).astype(np.int64)
        return j, i, inside

    def height(self, *, e, n) -> np.ndarray:
        """Surface height (ENU up, m) at points (e, n); NaN outside the grid."""
        e, n = np.broadcast_arrays(np.asarray(e, np.float64), np.asarray(n, np.float64))
        j, i, inside = self.cell_of(e=e, n=n)
        h = self._plane(j, i, e, n)
        return np.where(inside, h, np.nan)

    def _plane(self, j, i, e, n) -> np.ndarray:
        c = self.cell_m
        ec = self.e_min + (i + 0.5) * c
        nc = self.n_min + (j + 0.5) * c
        return self.top[j, i] + self.slope_e[j, i] * (e - ec) + self.slope_n[j, i] * (n - nc)


@dataclasses.dataclass(frozen=True)
class UnderTrees:
    """The cells a tree crown covers and what they held before the crowns were drawn."""

    j: np.ndarray  # (K,) int64 cell rows
    i: np.ndarray  # (K,) int64 cell columns
    top: np.ndarray  # (K,) float64
    slope_e: np.ndarray  # (K,) float64
    slope_n: np.ndarray  # (K,) float64
    material: np.ndarray  # (K,) uint8
    albedo: np.ndarray  # (K,) float32
    wall_albedo: np.ndarray  # (K,) float32


# ---------------------------------------------------------------------------------------------
# Bare ground
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class GroundShape:
    """Gently sloped ground: a plane plus a long-wavelength undulation (ENU metres).

    ``g(e, n) = slope_e * e + slope_n * n + amplitude * sin(k . (e, n) + phase)``, zero slope
    offset at the origin (the scene centre is at height ``amplitude * sin(phase)``).
    """

    slope_e: float  # dh/de of the plane
    slope_n: float  # dh/dn of the plane
    amplitude: float  # undulation amplitude (m)
    k_e: float  # undulation wave vector (rad/m)
    k_n: float
    phase: float  # rad

    def height(self, *, e, n) -> np.ndarray:
        e, n = np.asarray(e, np.float64), np.asarray(n, np.float64)
        return self.slope_e * e + self.slope_n * n + self.amplitude * np.sin(self.k_e * e + self.k_n * n + self.phase)

    def gradient(self, *, e, n) -> tuple[np.ndarray, np.ndarray]:
        e, n = np.asarray(e, np.float64), np.asarray(n, np.float64)
        c = self.amplitude * np.cos(self.k_e * e + self.k_n * n + self.phase)
        return self.slope_e + c * self.k_e, self.slope_n + c * self.k_n

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def random_ground(rng: np.random.Generator, *, half_diagonal_m: float) -> GroundShape:
    """A seeded gentle ground whose height stays within +-GROUND_RELIEF_M over the scene."""
    amplitude = rng.uniform(0.3, 1.2)
    slope = min(rng.uniform(0.004, 0.02), (GROUND_RELIEF_M - amplitude - 0.5) / max(half_diagonal_m, 1.0))
    slope_dir = rng.uniform(0.0, 2.0 * math.pi)
    wavelength = rng.uniform(120.0, 300.0)
    wave_dir = rng.uniform(0.0, 2.0 * math.pi)
    k = 2.0 * math.pi / wavelength
    return GroundShape(
        slope_e=slope * math.sin(slope_dir), slope_n=slope * math.cos(slope_dir),
        amplitude=amplitude, k_e=k * math.sin(wave_dir), k_n=k * math.cos(wave_dir),
        phase=rng.uniform(0.0, 2.0 * math.pi),
    )


# ---------------------------------------------------------------------------------------------
# Textures
# ---------------------------------------------------------------------------------------------
def value_noise(rng: np.random.Generator, shape: tuple[int, int], scale_cells: float) -> np.ndarray:
    """Smooth random field (zero mean, unit-ish amplitude) with features of ``scale_cells`` cells.

    Gaussian values on a lattice of spacing ``scale_cells`` are interpolated bilinearly.
    """
    ny, nx = shape
    s = max(float(scale_cells), 1.0)
    gy, gx = int(math.ceil(ny / s)) + 2, int(math.ceil(nx / s)) + 2
    lattice = rng.standard_normal((gy, gx))
    y = np.arange(ny) / s
    x = np.arange(nx) / s
    y0 = np.floor(y).astype(np.int64)
    x0 = np.floor(x).astype(np.int64)
    fy = (y - y0)[:, None]
    fx = (x - x0)[None, :]
    # Separable: each lattice row interpolated along x once, then those rows along y (the same
    # arithmetic as interpolating each cell's four lattice values: (a (1 - fx) + b fx) (1 - fy) +
    # (c (1 - fx) + d fx) fy).
    along_x = lattice[:, x0] * (1 - fx) + lattice[:, x0 + 1] * fx  # (gy, nx)
    return along_x[y0] * (1 - fy) + along_x[y0 + 1] * fy


def fractal_noise(rng: np.random.Generator, shape: tuple[int, int], scales_cells: tuple[float, ...],
                  gain: float = 0.6) -> np.ndarray:
    """Sum of value noises over several scales (largest first), normalised to unit std."""
    total = np.zeros(shape)
    w = 1.0
    for s in scales_cells:
        total += w * value_noise(rng, shape, s)
        w *= gain
    return total / max(float(total.std()), 1e-12)


# ---------------------------------------------------------------------------------------------
# Layout
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass
class _Canvas:
    """Mutable grid arrays while the layout is drawn."""

    grid: SurfaceGrid
    ec: np.ndarray  # (nx,) cell centre eastings
    nc: np.ndarray  # (ny,) cell centre northings

    def window(self, e0: float, n0: float, e1: float, n1: float) -> tuple[slice, slice]:
        """Slices of the cells whose centres lie in [e0, e1) x [n0, n1)."""
        g = self.grid
        c = g.cell_m
        i0 = int(np.clip(math.ceil((e0 - g.e_min) / c - 0.5), 0, len(self.ec)))
        i1 = int(np.clip(math.ceil((e1 - g.e_min) / c - 0.5), 0, len(self.ec)))
        j0 = int(np.clip(math.ceil((n0 - g.n_min) / c - 0.5), 0, len(self.nc)))
        j1 = int(np.clip(math.ceil((n1 - g.n_min) / c - 0.5), 0, len(self.nc)))
        return slice(j0, j1), slice(i0, i1)


def _ground_grid(ground: GroundShape, e_min: float, n_min: float, nx: int, ny: int, cell_m: float) -> SurfaceGrid:
    ec = e_min + (np.arange(nx) + 0.5) * cell_m
    nc = n_min + (np.arange(ny) + 0.5) * cell_m
    E, N = np.meshgrid(ec, nc)
    ge, gn = ground.gradient(e=E, n=N)
    return SurfaceGrid(
        e_min=e_min, n_min=n_min, cell_m=cell_m, top=ground.height(e=E, n=N),
        slope_e=np.array(ge, dtype=np.float64), slope_n=np.array(gn, dtype=np.float64),
        material=np.zeros((ny, nx), np.uint8), albedo=np.zeros((ny, nx), np.float32),
        wall_albedo=np.zeros((ny, nx), np.float32), ground=ground,
    )


def _split_positions(rng: np.random.Generator, lo: float, hi: float, spacing: tuple[float, float]) -> list[float]:
    """Road centre lines across [lo, hi] at random spacings."""
    out = []
    x = lo + rng.uniform(0.2, 0.8) * spacing[0]
    while x < hi:
        out.append(x)
        x += rng.uniform(*spacing)
    return out


def _split_lots(rng: np.random.Generator, rect: tuple[float, float, float, float], max_side: float,
                min_side: float, out: list) -> None:
    """Recursively split a rectangle (e0, n0, e1, n1) into lots no longer than ``max_side``."""
    e0, n0, e1, n1 = rect
    w, h = e1 - e0, n1 - n0
    if max(w, h) <= max_side or max(w, h) < 2 * min_side:
        out.append(rect)
        return
    f = rng.uniform(0.35, 0.65)
    if w >= h:
        m = e0 + f * w
        _split_lots(rng, (e0, n0, m, n1), max_side, min_side, out)
        _split_lots(rng, (m, n0, e1, n1), max_side, min_side, out)
    else:
        m = n0 + f * h
        _split_lots(rng, (e0, n0, e1, m), max_side, min_side, out)
        _split_lots(rng, (e0, m, e1, n1), max_side, min_side, out)


class _Town:
    """Draws the seeded town on a canvas. Each step uses its own random stream."""

    def __init__(self, canvas: _Canvas, seed: int, aoi_half_m: float):
        self.cv = canvas
        self.g = canvas.grid
        self.seed = seed
        self.aoi_half = aoi_half_m
        self.buildings: list[Building] = []
        self.trees: list[tuple[float, ...]] = []
        shape = self.g.top.shape
        tex = np.random.default_rng([seed, 11])
        c = self.g.cell_m
        # Texture fields shared by the materials (cell units: 1 cell = cell_m).
        self.fine = fractal_noise(tex, shape, (2.0 / c, 1.0 / c, 0.5 / c))
        self.coarse = fractal_noise(tex, shape, (24.0 / c, 8.0 / c, 3.0 / c))
        self.grain = tex.standard_normal(shape)

    def rng(self, k: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, 100 + k])

    # -- ground materials -------------------------------------------------------------------
    def draw_ground(self) -> None:
        g = self.g
        # Grass and soil: strong multi-scale texture.
        alb = 0.17 + 0.045 * self.coarse + 0.03 * self.fine + 0.01 * self.grain
        g.albedo[...] = np.clip(alb, 0.04, 0.5)
        g.material[...] = GROUND

    def draw_roads(self) -> list[tuple[float, float, float, float]]:
        """Street grid; returns the blocks (e0, n0, e1, n1) between the sidewalks."""
        g, rng = self.g, self.rng(1)
        lo_e, hi_e, lo_n, hi_n = g.e_min, g.e_max, g.n_min, g.n_max
        roads_e = _split_positions(rng, lo_e, hi_e, (55.0, 85.0))  # north-south roads at these e
        roads_n = _split_positions(rng, lo_n, hi_n, (50.0, 80.0))  # east-west roads at these n
        widths_e = [float(rng.choice([8.0, 10.0, 12.0])) for _ in roads_e]
        widths_n = [float(rng.choice([8.0, 10.0, 12.0])) for _ in roads_n]
        walk = 2.5
        cv = self.cv
        E, N = np.meshgrid(cv.ec, cv.nc)
        for x, w in zip(roads_e, widths_e):
            self._paint(SIDEWALK, cv.window(x - w / 2 - walk, lo_n, x + w / 2 + walk, hi_n), self._sidewalk_albedo)
        for y, w in zip(roads_n, widths_n):
            self._paint(SIDEWALK, cv.window(lo_e, y - w / 2 - walk, hi_e, y + w / 2 + walk), self._sidewalk_albedo)
        for x, w in zip(roads_e, widths_e):
            win = cv.window(x - w / 2, lo_n, x + w / 2, hi_n)
            self._paint(ROAD, win, self._road_albedo)
            # Dashed centre line: 3 m dashes every 9 m, 0.3 m wide (along north).
            dash = (np.abs(E[win] - x) < 0.15) & (np.mod(N[win] - lo_n, 9.0) < 3.0)
            g.albedo[win][dash] = 0.55
        for y, w in zip(roads_n, widths_n):
            win = cv.window(lo_e, y - w / 2, hi_e, y + w / 2)
            self._paint(ROAD, win, self._road_albedo)
            dash = (np.abs(N[win] - y) < 0.15) & (np.mod(E[win] - lo_e, 9.0) < 3.0)
            g.albedo[win][dash] = 0.55
        # Blocks between the road strips.
        def spans(centres, widths, lo, hi):
            edges = [lo - 1e3] + [v for c, w in zip(centres, widths) for v in (c - w / 2 - walk, c + w / 2 + walk)] + [hi + 1e3]
            return [(max(edges[k], lo), min(edges[k + 1], hi)) for k in range(0, len(edges), 2)
                    if min(edges[k + 1], hi) - max(edges[k], lo) > 4.0]
        blocks = []
        for a0, a1 in spans(roads_e, widths_e, lo_e, hi_e):
            for b0, b1 in spans(roads_n, widths_n, lo_n, hi_n):
                blocks.append((a0, b0, a1, b1))
        self.road_lines = (roads_e, widths_e, roads_n, widths_n)
        return blocks

    def _paint(self, material: int, win, albedo_fn) -> None:
        self.g.material[win] = material
        self.g.albedo[win] = albedo_fn(win)

    def _road_albedo(self, win) -> np.ndarray:
        return np.clip(0.10 + 0.008 * self.coarse[win] + 0.012 * self.fine[win] + 0.006 * self.grain[win], 0.03, 0.3)

    def _sidewalk_albedo(self, win) -> np.ndarray:
        cv = self.cv
        e = cv.ec[win[1]][None, :]
        n = cv.nc[win[0]][:, None]
        joints = (np.mod(e, 1.0) < 0.06) | (np.mod(n, 1.0) < 0.06)
        base = 0.32 + 0.015 * self.coarse[win] + 0.01 * self.grain[win]
        return np.clip(np.where(joints, base - 0.08, base), 0.05, 0.6)

    # -- blocks -------------------------------------------------------------------------------
    def draw_blocks(self, blocks) -> None:
        rng = self.rng(2)
        kinds = []
        for _ in blocks:
            r = rng.uniform()
            kinds.append("plaza" if r < 0.12 else "park" if r < 0.25 else "buildings")
        # Keep at least one built block and, when there are several blocks, one plaza.
        if blocks and "buildings" not in kinds:
            kinds[int(rng.integers(len(blocks)))] = "buildings"
        if len(blocks) >= 4 and "plaza" not in kinds:
            cands = [k for k, v in enumerate(kinds) if v == "park"] or [k for k, v in enumerate(kinds) if v == "buildings"][1:]
            if cands:
                kinds[int(rng.choice(cands))] = "plaza"
        for k, (block, kind) in enumerate(zip(blocks, kinds)):
            brng = np.random.default_rng([self.seed, 1000 + k])
            if kind == "plaza":
                self._plaza(brng, block)
            elif kind == "park":
                self._park(brng, block)
            else:
                self._built_block(brng, block)
        self._ensure_tall_building()

    def _plaza(self, rng, block) -> None:
        win = self.cv.window(*block)
        base = rng.uniform(0.38, 0.5)
        self.g.material[win] = PLAZA
        self.g.albedo[win] = np.clip(base + 0.004 * self.coarse[win] + 0.003 * self.grain[win], 0, 1)
        e0, n0, e1, n1 = block
        # Planter trees in a loose grid along the plaza edges.
        step = rng.uniform(10.0, 14.0)
        for x in np.arange(e0 + 4.0, e1 - 3.0, step):
            for y in (n0 + 4.0, n1 - 4.0):
                if rng.uniform() < 0.7:
                    self._tree(rng, x, y)

    def _park(self, rng, block) -> None:
        e0, n0, e1, n1 = block
        area = (e1 - e0) * (n1 - n0)
        for _ in range(int(area / 90.0)):
            self._tree(rng, rng.uniform(e0 + 2, e1 - 2), rng.uniform(n0 + 2, n1 - 2))

    def _built_block(self, rng, block) -> None:
        lots: list = []
        _split_lots(rng, block, max_side=rng.uniform(16.0, 36.0), min_side=7.0, out=lots)
        style = rng.choice(["low", "mid", "tower"], p=[0.45, 0.4, 0.15])
        for lot in lots:
            if rng.uniform() < 0.12:
                self._garden(rng, lot)
                continue
            self._building(rng, lot, block, str(style))

    def _garden(self, rng, lot) -> None:
        e0, n0, e1, n1 = lot
        for _ in range(int(rng.integers(1, 3))):
            self._tree(rng, rng.uniform(e0 + 1, e1 - 1), rng.uniform(n0 + 1, n1 - 1))

    def _building(self, rng, lot, block, style: str) -> None:
        e0, n0, e1, n1 = lot
        # Sides on the block boundary keep a small setback from the sidewalk; inner sides are
        # often 0 so that neighbours share a wall (adjacent buildings of different heights).
        def setback(on_edge: bool) -> float:
            if on_edge:
                return float(rng.uniform(0.0, 2.0))
            return 0.0 if rng.uniform() < 0.6 else float(rng.uniform(1.0, 3.0))
        be0, bn0, be1, bn1 = block
        e0 += setback(abs(e0 - be0) < 1e-9)
        e1 -= setback(abs(e1 - be1) < 1e-9)
        n0 += setback(abs(n0 - bn0) < 1e-9)
        n1 -= setback(abs(n1 - bn1) < 1e-9)
        if min(e1 - e0, n1 - n0) < 4.0:
            self._garden(rng, lot)
            return
        floors = {"low": (1, 4), "mid": (3, 8), "tower": (8, 19)}[style]
        n_floors = int(rng.integers(floors[0], floors[1] + 1))
        wall_h = float(np.clip(STOREY_M * n_floors + rng.uniform(0.3, 1.2), MIN_BUILDING_M, MAX_BUILDING_M))
        gable = style == "low" and min(e1 - e0, n1 - n0) <= 22.0 and rng.uniform() < 0.55
        self._add_building(rng, e0, n0, e1, n1, wall_h, gable)

    def _add_building(self, rng, e0, n0, e1, n1, wall_h: float, gable: bool) -> None:
        g, cv = self.g, self.cv
        corners = g.ground.height(e=np.array([e0, e1, e0, e1]), n=np.array([n0, n0, n1, n1]))
        base = float(np.max(corners))
        win = cv.window(e0, n0, e1, n1)
        if win[0].start >= win[0].stop or win[1].start >= win[1].stop:
            return
        facade = float(rng.uniform(0.25, 0.6))
        if gable:
            pitch = math.radians(rng.uniform(25.0, 40.0))
            along_e = (e1 - e0) >= (n1 - n0)
            half = 0.5 * ((n1 - n0) if along_e else (e1 - e0))
            rise = half * math.tan(pitch)
            if wall_h + rise > MAX_BUILDING_M:
                rise = MAX_BUILDING_M - wall_h
            slope = rise / half
            E, N = np.meshgrid(cv.ec[win[1]], cv.nc[win[0]])
            if along_e:
                mid = 0.5 * (n0 + n1)
                dist = N - mid
                top = base + wall_h + rise - slope * np.abs(dist)
                g.slope_e[win] = 0.0
                g.slope_n[win] = -slope * np.sign(dist)
            else:
                mid = 0.5 * (e0 + e1)
                dist = E - mid
                top = base + wall_h + rise - slope * np.abs(dist)
                g.slope_e[win] = -slope * np.sign(dist)
                g.slope_n[win] = 0.0
            g.top[win] = top
            g.material[win] = ROOF_GABLE
            rows = np.mod(np.abs(dist), 0.5) < 0.1  # tile courses
            base_alb = rng.uniform(0.18, 0.32)
            g.albedo[win] = np.clip(base_alb + np.where(rows, -0.04, 0.0) + 0.02 * self.fine[win] + 0.01 * self.grain[win], 0.03, 0.7)
            height = wall_h + rise
        else:
            g.top[win] = base + wall_h
            g.slope_e[win] = 0.0
            g.slope_n[win] = 0.0
            g.material[win] = ROOF
            base_alb = rng.uniform(0.3, 0.62)
            if rng.uniform() < 0.3:  # gravel roof: textured
                alb = base_alb + 0.04 * self.fine[win] + 0.02 * self.grain[win]
            else:  # plain membrane: weakly textured
                alb = base_alb + 0.004 * self.coarse[win] + 0.002 * self.grain[win]
            g.albedo[win] = np.clip(alb, 0.03, 0.9)
            height = wall_h
            area = (e1 - e0) * (n1 - n0)
            if area > 200.0 and rng.uniform() < 0.6:
                for _ in range(int(rng.integers(1, 4))):
                    w, d = rng.uniform(2.0, 5.0, size=2)
                    if e1 - e0 < w + 2 or n1 - n0 < d + 2:
                        continue
                    x = rng.uniform(e0 + 1, e1 - 1 - w)
                    y = rng.uniform(n0 + 1, n1 - 1 - d)
                    box_h = min(rng.uniform(1.2, 3.0), MAX_BUILDING_M - wall_h)
                    if box_h <= 0.2:
                        continue
                    bwin = cv.window(x, y, x + w, y + d)
                    g.top[bwin] = base + wall_h + box_h
                    g.material[bwin] = ROOF_BOX
                    g.albedo[bwin] = np.clip(rng.uniform(0.45, 0.75) + 0.01 * self.grain[bwin], 0, 1)
                    g.wall_albedo[bwin] = float(rng.uniform(0.4, 0.7))
                    height = max(height, wall_h + box_h)
        g.wall_albedo[win] = np.where(g.material[win] == ROOF_BOX, g.wall_albedo[win], facade)
        self.buildings.append(Building(e0=float(e0), n0=float(n0), e1=float(e1), n1=float(n1), base_u=base,
                                       height_m=float(height), roof="gable" if gable else "flat"))

    def _ensure_tall_building(self) -> None:
        """Raise the largest flat building inside the AOI to a tower when none exceeds 40 m."""
        inside = [k for k, b in enumerate(self.buildings)
                  if max(abs(b.e0), abs(b.e1), abs(b.n0), abs(b.n1)) <= self.aoi_half]
        if not inside or max(self.buildings[k].height_m for k in inside) >= 40.0:
            return
        flat = [k for k in inside if self.buildings[k].roof == "flat"]
        if not flat:
            return
        k = max(flat, key=lambda k: (self.buildings[k].e1 - self.buildings[k].e0) * (self.buildings[k].n1 - self.buildings[k].n0))
        b = self.buildings[k]
        rng = self.rng(3)
        new_h = float(rng.uniform(45.0, MAX_BUILDING_M - 1.0))
        win = self.cv.window(b.e0, b.n0, b.e1, b.n1)
        # Lift the whole building (roof boxes included, crowns overhanging it not) to new_h.
        self.g.top[win] += new_h - b.height_m
        self.buildings[k] = dataclasses.replace(b, height_m=new_h)

    # -- trees ----------------------------------------------------------------------------------
    def draw_street_trees(self) -> None:
        rng = self.rng(4)
        roads_e, widths_e, roads_n, widths_n = self.road_lines
        g = self.g
        for x, w in zip(roads_e, widths_e):
            if rng.uniform() < 0.5:
                for side in (-1, 1):
                    for y in np.arange(g.n_min + rng.uniform(0, 10), g.n_max, rng.uniform(9.0, 13.0)):
                        if rng.uniform() < 0.7:
                            self._tree(rng, x + side * (w / 2 + 1.2), y, small=True)
        for y, w in zip(roads_n, widths_n):
            if rng.uniform() < 0.5:
                for side in (-1, 1):
                    for x in np.arange(g.e_min + rng.uniform(0, 10), g.e_max, rng.uniform(9.0, 13.0)):
                        if rng.uniform() < 0.7:
                            self._tree(rng, x, y + side * (w / 2 + 1.2), small=True)

    def _tree(self, rng, x: float, y: float, small: bool = False) -> None:
        """Draw a tree's size now; it is planted by ``draw_trees`` after all buildings."""
        radius = rng.uniform(1.6, 2.8) if small else rng.uniform(2.0, 4.5)
        total = rng.uniform(5.0, 9.0) if small else rng.uniform(6.0, MAX_TREE_M)
        depth = min(radius * rng.uniform(0.7, 1.1), total - 2.0)
        self.trees.append((float(x), float(y), float(radius), float(total), float(depth), float(rng.uniform(0.07, 0.13))))

    def draw_trees(self) -> None:
        for tree in self.trees:
            self._plant(*tree)

    def _plant(self, x: float, y: float, radius: float, total: float, depth: float, leaf_albedo: float) -> None:
        """An ellipsoidal crown: u = crown_base + depth * sqrt(1 - (r/R)^2), over the ground."""
        g, cv = self.g, self.cv
        ground = float(g.ground.height(e=x, n=y))
        crown_base = ground + total - depth
        win = cv.window(x - radius, y - radius, x + radius, y + radius)
        if win[0].start >= win[0].stop or win[1].start >= win[1].stop:
            return
        E, N = np.meshgrid(cv.ec[win[1]], cv.nc[win[0]])
        q = ((E - x) ** 2 + (N - y) ** 2) / radius ** 2
        inside = q < 0.98
        root = np.sqrt(np.clip(1.0 - q, 1e-6, None))
        h = crown_base + depth * root
        # Gradient of the ellipsoid cap, clamped where it becomes vertical at the rim.
        ge = np.clip(-depth * (E - x) / (radius ** 2 * root), -6.0, 6.0)
        gn = np.clip(-depth * (N - y) / (radius ** 2 * root), -6.0, 6.0)
        higher = inside & (h > g.top[win])
        tw = (slice(win[0].start, win[0].stop), slice(win[1].start, win[1].stop))
        g.top[tw][higher] = h[higher]
        g.slope_e[tw][higher] = ge[higher]
        g.slope_n[tw][higher] = gn[higher]
        g.material[tw][higher] = TREE
        leaf = np.clip(leaf_albedo + 0.035 * self.fine[tw] + 0.02 * self.grain[tw], 0.02, 0.3)
        g.albedo[tw][higher] = leaf[higher]
        g.wall_albedo[tw][higher] = leaf[higher]


def build_surface(*, seed: int, e_min: float, n_min: float, e_max: float, n_max: float,
                  cell_m: float, aoi_half_m: float) -> SurfaceGrid:
    """Draw the seeded town on a grid covering [e_min, e_max] x [n_min, n_max] (ENU m).

    The same arguments always give the same surface (every random draw comes from a stream
    seeded with ``seed`` and a fixed stream number). ``aoi_half_m``: half-size of the area of
    interest (centred on the origin), where at least one tall building is guaranteed.
    """
    nx = int(math.ceil((e_max - e_min) / cell_m - 1e-9))
    ny = int(math.ceil((n_max - n_min) / cell_m - 1e-9))
    half_diag = math.hypot(max(abs(e_min), abs(e_max)), max(abs(n_min), abs(n_max)))
    ground = random_ground(np.random.default_rng([seed, 1]), half_diagonal_m=half_diag)
    grid = _ground_grid(ground, e_min, n_min, nx, ny, cell_m)
    canvas = _Canvas(grid=grid, ec=grid.cell_centres()[0], nc=grid.cell_centres()[1])
    town = _Town(canvas, seed, aoi_half_m)
    town.draw_ground()
    blocks = town.draw_roads()
    town.draw_blocks(blocks)
    town.draw_street_trees()
    before = (grid.top.copy(), grid.slope_e.copy(), grid.slope_n.copy(), grid.material.copy(),
              grid.albedo.copy(), grid.wall_albedo.copy())
    town.draw_trees()
    grid.buildings = tuple(town.buildings)
    grid.roads = tuple(tuple(float(v) for v in part) for part in town.road_lines)
    grid.trees = tuple(town.trees)
    j, i = np.nonzero(grid.material == TREE)
    grid.under_trees = UnderTrees(j=j, i=i, top=before[0][j, i], slope_e=before[1][j, i],
                                  slope_n=before[2][j, i], material=before[3][j, i],
                                  albedo=before[4][j, i], wall_albedo=before[5][j, i])
    return grid


# ---------------------------------------------------------------------------------------------
# Ray casting
# ---------------------------------------------------------------------------------------------
FACE_TOP = 0  # the ray hit the plane of the cell
FACE_E = 1  # the ray hit the wall on the cell's west or east edge (normal along e)
FACE_N = 2  # the ray hit the wall on the cell's south or north edge (normal along n)


@dataclasses.dataclass
class RayHits:
    """First intersections of rays with the surface (one entry per ray)."""

    point: np.ndarray  # (N, 3) ENU hit points (m): exactly origin + t * direction
    t: np.ndarray  # (N,) ray parameter of the hit
    j: np.ndarray  # (N,) int: cell row of the hit (the cell whose plane or wall was hit)
    i: np.ndarray  # (N,) int: cell column
    face: np.ndarray  # (N,) int8: FACE_TOP, FACE_E or FACE_N
    normal: np.ndarray  # (N, 3) unit surface normal at the hit (walls: horizontal, facing the ray)
    wall_depth: np.ndarray  # (N,) m below the cell's top edge where a wall was hit (0 for tops)


# Cells per side of the blocks of the empty-space skipping pass of ``cast_rays``.
COARSE_BLOCK = 16


def _block_max(grid: SurfaceGrid, block: int) -> np.ndarray:
    """Highest surface point of each block of block x block cells (-inf beyond the grid)."""
    ny, nx = grid.top.shape
    nby, nbx = -(-ny // block), -(-nx // block)
    reach = 0.5 * grid.cell_m * (np.abs(grid.slope_e) + np.abs(grid.slope_n))
    pad = np.full((nby * block, nbx * block), -np.inf)
    pad[:ny, :nx] = grid.top + reach
    return pad.reshape(nby, block, nbx, block).max(axis=(1, 3))


def _grid_exits(e0, n0, size, bi, bj, ox, oy, dx, dy) -> tuple[np.ndarray, np.ndarray]:
    """Ray parameters at which rays leave grid cell (bj, bi) of a grid of ``size`` m squares
    through its east/west and its north/south edges (inf for rays parallel to those edges)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_e = np.where(dx != 0.0, (e0 + (bi + (dx > 0)) * size - ox) / np.where(dx != 0.0, dx, 1.0), np.inf)
        t_n = np.where(dy != 0.0, (n0 + (bj + (dy > 0)) * size - oy) / np.where(dy != 0.0, dy, 1.0), np.inf)
    return t_e, t_n


# The walks below leave finished rays in their arrays (frozen in the cell where they finished)
# and compact the arrays only once fewer than this fraction of their rays still walk: gathering
# every per-ray array at each step cost about a third of the walk. Any value gives the same hits.
WALK_COMPACT_FRACTION = 0.75


class _Walk:
    """The per-ray arrays of a vectorised walk, compacted together (``live``: still walking)."""

    def __init__(self, **arrays: np.ndarray):
        self.arrays = arrays
        self.ray = np.arange(next(iter(arrays.values())).shape[0])  # index in the caller's rays
        self.live = np.ones(self.ray.size, bool)
        self.n_live = self.ray.size

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None

    def update(self, **arrays: np.ndarray) -> None:
        self.arrays.update(arrays)

    def finish(self, finished: np.ndarray) -> None:
        """Mark the rays of boolean ``finished`` (live ones only) as done; compact if few walk."""
        self.live &= ~finished
        self.n_live = int(np.count_nonzero(self.live))
        if self.n_live < WALK_COMPACT_FRACTION * self.ray.size:
            keep = np.flatnonzero(self.live)
            self.arrays = {k: v[keep] for k, v in self.arrays.items()}
            self.ray = self.ray[keep]
            self.live = np.ones(keep.size, bool)

    def check_inside(self, i: np.ndarray, j: np.ndarray, nx: int, ny: int, what: str) -> None:
        # The walks' int64 indices as unsigned integers: the negative ones are beyond any size,
        # so two comparisons check both bounds.
        inside = (i.view(np.uint64) < nx) & (j.view(np.uint64) < ny)
        if not inside.all():
            out = int(np.count_nonzero(~inside & self.live))
            if out:
                raise RuntimeError(f"{out} ray(s) left the {what} without a hit: "
                                   "the grid does not cover the views' footprints")


def _skip_empty_blocks(grid: SurfaceGrid, origin: np.ndarray, direction: np.ndarray, t0: np.ndarray,
                       block: int, bmax: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Walk rays over blocks of cells from parameter ``t0`` to the first block whose highest
    point (``bmax``, ``_block_max(grid, block)``) the ray reaches before leaving it; return (t, i,
    j, face) where the fine walk starts: the ray parameter where it entered that block, the cell
    there, and the face it entered by (FACE_TOP for the first block). Every block passed over
    lies wholly below the ray."""
    size = grid.cell_m * block
    nby, nbx = bmax.shape
    bmax_flat = bmax.ravel()
    ox, oy, oz = origin[:, 0], origin[:, 1], origin[:, 2]
    dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
    n = ox.size
    out_t, out_face = np.empty(n), np.empty(n, np.int8)
    out_bi, out_bj = np.empty(n, np.int64), np.empty(n, np.int64)
    w = _Walk(ox=ox, oy=oy, oz=oz, dx=dx, dy=dy, dz=dz,
              step_i=np.where(dx > 0, 1, -1), step_j=np.where(dy > 0, 1, -1),
              bi=np.floor((ox + t0 * dx - grid.e_min) / size).astype(np.int64),
              bj=np.floor((oy + t0 * dy - grid.n_min) / size).astype(np.int64),
              t=t0.copy(), face=np.zeros(n, np.int8))
    while w.n_live:
        bi, bj = w.bi, w.bj
        w.check_inside(bi, bj, nbx, nby, "surface grid")
        t_e, t_n = _grid_exits(grid.e_min, grid.n_min, size, bi, bj, w.ox, w.oy, w.dx, w.dy)
        t_out = np.minimum(t_e, t_n)
        stop = (w.oz + t_out * w.dz <= bmax_flat[bj * nbx + bi]) & w.live
        if stop.any():
            k = w.ray[stop]
            out_t[k], out_face[k] = w.t[stop], w.face[stop]
            out_bi[k], out_bj[k] = bi[stop], bj[stop]
        go = w.live & ~stop
        cross_e = t_e <= t_n
        w.update(t=np.where(go, t_out, w.t), bi=bi + np.where(cross_e & go, w.step_i, 0),
                 bj=bj + np.where(~cross_e & go, w.step_j, 0),
                 face=np.where(cross_e, FACE_E, FACE_N).astype(np.int8))
        w.finish(stop)
    # The starting cell: where the ray is at out_t, kept inside its block against rounding.
    ny, nx = grid.top.shape
    fi = np.floor((ox + out_t * dx - grid.e_min) / grid.cell_m).astype(np.int64)
    fj = np.floor((oy + out_t * dy - grid.n_min) / grid.cell_m).astype(np.int64)
    i = np.clip(fi, out_bi * block, np.minimum(out_bi * block + block, nx) - 1)
    j = np.clip(fj, out_bj * block, np.minimum(out_bj * block + block, ny) - 1)
    return out_t, i, j, out_face


def cast_rays(grid: SurfaceGrid, origin: np.ndarray, direction: np.ndarray) -> RayHits:
    """``RayCaster(grid).cast(origin, direction)``: for rays cast at one surface in several
    calls, make one ``RayCaster``."""
    return RayCaster(grid).cast(origin, direction)


class RayCaster:
    """Ray casting at one surface: what every cast needs of ``grid`` (its highest point, its
    blocks' highest points) computed once. ``grid`` must not change while this is used."""

    def __init__(self, grid: SurfaceGrid):
        self.grid = grid
        self.z_top = grid.max_height() + 1e-6
        self.block_max = _block_max(grid, COARSE_BLOCK)

    def cast(self, origin: np.ndarray, direction: np.ndarray) -> RayHits:
        """Exact first hit of downward rays ``origin + t * direction`` (t > 0) with the surface.

        A 2D digital differential analyser (Amanatides & Woo) walks the cells the ray crosses,
        from where it enters the slab below the highest surface point; in each cell the ray is
        tested against the wall on the edge it entered through (the ray is below the cell's
        plane there) and against the cell's plane (closed-form intersection inside the cell). A
        first, coarser walk over blocks of COARSE_BLOCK^2 cells skips the blocks that lie wholly
        below the ray. Vectorised over rays; each iteration advances every unfinished ray by one
        cell (block). Raises RuntimeError if a ray leaves the grid before hitting (the grid must
        cover the rays' footprint).
        """
        origin = np.asarray(origin, np.float64).reshape(-1, 3)
        direction = np.asarray(direction, np.float64).reshape(-1, 3)
        nray = origin.shape[0]
        if np.any(direction[:, 2] >= 0.0):
            raise ValueError("cast_rays needs downward rays (direction u < 0)")
        grid = self.grid
        c = grid.cell_m
        ny, nx = grid.top.shape
        z_top = self.z_top
        ox, oy, oz = origin[:, 0], origin[:, 1], origin[:, 2]
        dx, dy, dz = direction[:, 0], direction[:, 1], direction[:, 2]
        t_top = (z_top - oz) / dz
        t_in, i, j, face_in = _skip_empty_blocks(grid, origin, direction, t_top, COARSE_BLOCK,
                                                 self.block_max)
        step_i = np.where(dx > 0, 1, -1)
        step_j = np.where(dy > 0, 1, -1)
        # Rays parallel to a grid axis never cross the edges across it (t = inf there).
        moves_e, moves_n = dx != 0.0, dy != 0.0
        all_e, all_n = bool(moves_e.all()), bool(moves_n.all())
        top_flat, ge_flat, gn_flat = grid.top.ravel(), grid.slope_e.ravel(), grid.slope_n.ravel()

        hit_t = np.empty(nray)
        hit_j = np.empty(nray, np.int64)
        hit_i = np.empty(nray, np.int64)
        hit_face = np.empty(nray, np.int8)
        hit_depth = np.zeros(nray)

        w = _Walk(ox=ox, oy=oy, oz=oz, dx=dx, dy=dy, dz=dz, step_i=step_i, step_j=step_j,
                  moves_e=moves_e, moves_n=moves_n,
                  inv_dx=1.0 / np.where(moves_e, dx, 1.0), inv_dy=1.0 / np.where(moves_n, dy, 1.0),
                  edge_i=(dx > 0).astype(np.int64),  # +1: the exit edge is the east one
                  edge_j=(dy > 0).astype(np.int64), i=i, j=j, t=t_in, face=face_in)
        # Per column / row: the cells' centres and their edges (the same arithmetic as on
        # each ray's index: a lookup per step instead of three operations).
        e_centre = grid.e_min + (np.arange(nx) + 0.5) * c
        n_centre = grid.n_min + (np.arange(ny) + 0.5) * c
        e_edge = grid.e_min + np.arange(nx + 1) * c
        n_edge = grid.n_min + np.arange(ny + 1) * c
        while w.n_live:
            a_i, a_j, a_t, a_face = w.i, w.j, w.t, w.face
            w.check_inside(a_i, a_j, nx, ny, f"{nx}x{ny} surface grid")
            cell = a_j * nx + a_i
            top, ge, gn = top_flat[cell], ge_flat[cell], gn_flat[cell]
            ec = e_centre[a_i]
            nc = n_centre[a_j]
            # F(t) = ray height - plane height, linear in t: F0 + F1 * t.
            f0 = w.oz - top - ge * (w.ox - ec) - gn * (w.oy - nc)
            f1 = w.dz - ge * w.dx - gn * w.dy
            t_e = (e_edge[a_i + w.edge_i] - w.ox) * w.inv_dx
            t_n = (n_edge[a_j + w.edge_j] - w.oy) * w.inv_dy
            if not all_e:
                t_e = np.where(w.moves_e, t_e, np.inf)
            if not all_n:
                t_n = np.where(w.moves_n, t_n, np.inf)
            t_out = np.minimum(t_e, t_n)
            f_in = f0 + f1 * a_t
            wall = (f_in <= 0.0) & (a_face != FACE_TOP)
            f_out = f0 + f1 * t_out
            plane = ~wall & (f_out <= 0.0)
            done = (wall | plane) & w.live
            if done.any():
                sel = np.flatnonzero(done)
                on_wall, f0_s, f1_s, t_s = wall[sel], f0[sel], f1[sel], a_t[sel]
                with np.errstate(divide="ignore", invalid="ignore"):
                    t_plane = np.where(plane[sel], -f0_s / np.where(f1_s != 0.0, f1_s, -1.0), t_s)
                t_plane = np.clip(t_plane, t_s, t_out[sel])  # rounding guard: stay inside the cell
                ray = w.ray[sel]
                hit_t[ray] = np.where(on_wall, t_s, t_plane)
                hit_j[ray] = a_j[sel]
                hit_i[ray] = a_i[sel]
                hit_face[ray] = np.where(on_wall, a_face[sel], FACE_TOP)
                hit_depth[ray] = np.where(on_wall, -f_in[sel], 0.0)
            go = w.live & ~done
            cross_e = t_e <= t_n
            w.update(t=np.where(go, t_out, a_t), i=a_i + np.where(cross_e & go, w.step_i, 0),
                     j=a_j + np.where(~cross_e & go, w.step_j, 0),
                     face=np.where(cross_e, np.int8(FACE_E), np.int8(FACE_N)))
            w.finish(done)

        point = origin + hit_t[:, None] * direction
        ge = grid.slope_e[hit_j, hit_i]
        gn = grid.slope_n[hit_j, hit_i]
        normal = np.stack([-ge, -gn, np.ones(nray)], axis=1)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        on_e = hit_face == FACE_E
        on_n = hit_face == FACE_N
        normal[on_e] = np.stack([-step_i[on_e], np.zeros(on_e.sum()), np.zeros(on_e.sum())], axis=1)
        normal[on_n] = np.stack([np.zeros(on_n.sum()), -step_j[on_n], np.zeros(on_n.sum())], axis=1)
        return RayHits(point=point, t=hit_t, j=hit_j, i=hit_i, face=hit_face, normal=normal,
                       wall_depth=hit_depth)


# ---------------------------------------------------------------------------------------------
# Sun shadows
# ---------------------------------------------------------------------------------------------
def sun_vector(*, elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit ENU vector pointing towards the sun."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])


class ShadowMap:
    """Which points see the sun, from a horizon map along the sun's azimuth.

    The surface is sampled on a grid rotated so that its rows run towards the sun (spacing
    ``cell_m``); along each row, a reverse running maximum gives the occluding height
    ``S(p) = max over samples q ahead of p (h(q) - |q - p| tan(elevation))``. A point at height
    ``u`` is lit when ``u >= S - SHADOW_TOLERANCE_M`` at its nearest row, taking the samples
    strictly ahead of it. Accurate to about one cell at shadow edges (shading only; the geometry
    of the scene does not depend on it).
    """

    def __init__(self, grid: SurfaceGrid, sun: np.ndarray):
        self.sun = np.asarray(sun, np.float64)
        h = self.sun[:2]
        if np.linalg.norm(h) < 1e-9:  # sun at the zenith: no cast shadows
            h = np.array([0.0, 1.0])
        self.fwd = h / np.linalg.norm(h)
        self.side = np.array([self.fwd[1], -self.fwd[0]])
        self.tan_el = self.sun[2] / max(float(np.linalg.norm(self.sun[:2])), 1e-12)
        self.step = grid.cell_m
        corners = np.array([[grid.e_min, grid.n_min], [grid.e_max, grid.n_min],
                            [grid.e_min, grid.n_max], [grid.e_max, grid.n_max]])
        a = corners @ self.fwd
        b = corners @ self.side
        self.a0, self.b0 = float(a.min()), float(b.min())
        na = int(math.ceil((a.max() - self.a0) / self.step)) + 1
        nb = int(math.ceil((b.max() - self.b0) / self.step)) + 1
        av = self.a0 + np.arange(na) * self.step
        self.occluder = np.empty((nb, na))
        for k0 in range(0, nb, 256):
            bv = self.b0 + np.arange(k0, min(k0 + 256, nb)) * self.step
            E = av[None, :] * self.fwd[0] + bv[:, None] * self.side[0]
            N = av[None, :] * self.fwd[1] + bv[:, None] * self.side[1]
            hs = grid.height(e=E, n=N)
            q = np.where(np.isnan(hs), -np.inf, hs - av[None, :] * self.tan_el)
            run = np.maximum.accumulate(q[:, ::-1], axis=1)[:, ::-1]
            occ = np.full(q.shape, -np.inf)
            occ[:, :-1] = run[:, 1:] + av[None, :-1] * self.tan_el
            self.occluder[k0:k0 + bv.size] = occ
        self.na, self.nb = na, nb

    def lit(self, points: np.ndarray) -> np.ndarray:
        """Boolean: do the ENU points (N, 3) see the sun (no cast shadow)?"""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        a = p[:, :2] @ self.fwd
        b = p[:, :2] @ self.side
        ka = np.clip(np.floor((a - self.a0) / self.step).astype(np.int64), 0, self.na - 1)
        kb = np.clip(np.rint((b - self.b0) / self.step).astype(np.int64), 0, self.nb - 1)
        # Occluders from the sample ahead of the point's own (which may lie behind it).
        occ = self.occluder[kb, ka] + (a - (self.a0 + ka * self.step)) * self.tan_el
        return p[:, 2] >= occ - SHADOW_TOLERANCE_M


# ---------------------------------------------------------------------------------------------
# Shading
# ---------------------------------------------------------------------------------------------
# Share of the irradiance that is diffuse sky light (reaches shadows and faces turned away).
AMBIENT = 0.25
# Facade pattern: a window band in every storey and window columns along the wall (m).
WINDOW_BAND_M = (0.9, 2.2)
WINDOW_PERIOD_M = 2.6
WINDOW_WIDTH_M = 1.4
WINDOW_DARKENING = 0.45


# Vegetation's colour in the 8-bit RGB deliveries (``satsweep.synth.scene.to_rgb8``): the
# greenness of a hit is TREE_GREENNESS times its cell's leafiness on a crown (its top or its
# flank), GRASS_GREENNESS on grass and soil, 0 elsewhere (roads, paving, roofs, facades, cars).
# Real pansharpened RGB shows leaves green and lawns a duller green; what a vegetation index
# has to tell apart is a crown from a lawn, and a crown in leaf from one without leaves.
TREE_GREENNESS = 1.0
GRASS_GREENNESS = 0.5


def greenness(grid: SurfaceGrid, hits: RayHits) -> np.ndarray:
    """Per hit, the greenness of the surface it shows (see TREE_GREENNESS), 0..1."""
    mat = grid.material[hits.j, hits.i]
    leaves = (np.ones(mat.shape) if grid.leafiness is None
              else grid.leafiness[hits.j, hits.i].astype(np.float64))
    out = np.where(mat == TREE, TREE_GREENNESS * leaves, 0.0)
    return np.where(mat == GROUND, GRASS_GREENNESS, out)


def shade(grid: SurfaceGrid, hits: RayHits, shadows: ShadowMap) -> np.ndarray:
    """Lambertian radiance (albedo units, 0..1) at the hits: albedo * (ambient + direct)."""
    j, i = hits.j, hits.i
    facade = (hits.face != FACE_TOP) & (hits.wall_depth >= MIN_WALL_M)
    normal = hits.normal.copy()
    # Low "walls" are cell steps of the ground or of a crown: shade them as the top plane.
    low = (hits.face != FACE_TOP) & ~facade
    if np.any(low):
        ge, gn = grid.slope_e[j[low], i[low]], grid.slope_n[j[low], i[low]]
        nrm = np.stack([-ge, -gn, np.ones(ge.size)], axis=1)
        normal[low] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    albedo = grid.albedo[j, i].astype(np.float64)
    if np.any(facade):
        p = hits.point[facade]
        mat = grid.material[j[facade], i[facade]]
        wall = grid.wall_albedo[j[facade], i[facade]].astype(np.float64)
        along = np.where(hits.face[facade] == FACE_E, p[:, 1], p[:, 0])
        above = p[:, 2] - grid.ground.height(e=p[:, 0], n=p[:, 1])
        level = np.mod(above, STOREY_M)
        window = ((level > WINDOW_BAND_M[0]) & (level < WINDOW_BAND_M[1])
                  & (np.mod(along, WINDOW_PERIOD_M) < WINDOW_WIDTH_M)
                  & ((mat == ROOF) | (mat == ROOF_GABLE)))
        wall = np.where(window, wall * WINDOW_DARKENING, wall)
        # Trees show their own leaves on their flanks.
        albedo[facade] = np.where(mat == TREE, albedo[facade], wall)
    cos_sun = np.clip(normal @ shadows.sun, 0.0, None)
    probe = hits.point.copy()
    # Wall points are tested from one cell in front of the wall, so that the wall's own building
    # (beside the sample row when the sun grazes the wall) does not shadow it.
    probe[facade, :2] += grid.cell_m * hits.normal[facade, :2]
    lit = shadows.lit(probe) & (cos_sun > 0.0)
    return albedo * (AMBIENT + (1.0 - AMBIENT) * cos_sun * lit)
