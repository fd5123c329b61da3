"""A ChArUco board drawn through hwsim's camera, for calibrating clothd against a known camera.

The board is evaluated analytically, not from a raster: each sample point on the board plane is paper,
a dark square or a marker cell, from OpenCV's own layout of the board (`cv2.aruco.CharucoBoard`:
marker positions and ids, and the marker bits of its dictionary). A picture is rendered by inverse
mapping: for each of supersample² points inside a pixel, the pixel is undistorted into a viewing ray
(lens distortion inverted once per pixel corner and interpolated inside the pixel, where it is linear
to far below 1e-6 px), the ray meets the board plane, and the board is sampled there; the mean is the
pixel's value (an area filter, as a sensor integrates). The points inside a pixel lie on a sheared
grid (`sample_offsets`), so that an edge square to the image is not quantised to 1/supersample px.
Corners land where the camera's own projection puts them, with nothing from OpenCV's drawing in
between; `to_grey8` then adds the lens's blur and the sensor's noise. OpenCV's detector finds the
corners 0.05 px from their true projection on average, the same at 4 x 4 as at 8 x 8 samples per
pixel: what is left is the detector's.

Board frame: OpenCV's. x along a row of corner ids, y down the rows, z into the board (away from the
side that is seen); the board's outer corner at (0, 0), ChArUco corner id 0 at (square, square).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hwsim.camera import Camera

PAPER = 0.85  # grey levels of 1: white paper, printed black, and the table around the board
INK = 0.06
TABLE = 0.40
LENS_BLUR_PX = 0.7  # a real lens spreads a point over about a pixel and a half
MARGIN_SQUARES = 0.5  # white paper around the printed squares, in squares: detection needs a quiet zone
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: squares_x x squares_y squares of square_m, markers of marker_m from `dictionary`
    (a cv2.aruco predefined name such as DICT_5X5_100)."""

    squares_x: int = 9
    squares_y: int = 6
    square_m: float = 0.060
    marker_m: float = 0.045
    dictionary: str = "DICT_5X5_100"

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, dictionary
        )

    @property
    def size_m(self) -> tuple[float, float]:
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def corners_m(self) -> np.ndarray:
        """ChArUco corners in the board frame, (n, 3), in id order."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64)


class BoardPattern:
    """Where the board is dark: `ink(points_m)` for board-plane points (n, 2)."""

    def __init__(self, spec: BoardSpec) -> None:
        board = spec.cv_board()
        dictionary = board.getDictionary()
        cells = dictionary.markerSize + 2  # the marker's bits and its one-cell black border
        self.spec = spec
        self.cells = cells
        shape = (spec.squares_y, spec.squares_x)
        self.dark_square = np.ones(shape, dtype=bool)  # squares without a marker are printed black
        self.marker_of_square = np.full(shape, -1)
        self.marker_origin_m = np.zeros((*shape, 2))
        bits = []
        for k, (corners, marker_id) in enumerate(
            zip(board.getObjPoints(), np.asarray(board.getIds()).ravel(), strict=True)
        ):
            xy = np.asarray(corners, dtype=np.float64).reshape(-1, 3)[:, :2]
            i, j = (xy.mean(axis=0) // spec.square_m).astype(int)
            self.dark_square[j, i] = False
            self.marker_of_square[j, i] = k
            self.marker_origin_m[j, i] = xy.min(axis=0)
            # One pixel per cell: the marker's bit grid exactly.
            bits.append(cv2.aruco.generateImageMarker(dictionary, int(marker_id), cells, borderBits=1) == 0)
        self.marker_bits = np.asarray(bits)  # (markers, cells, cells), True where dark

    def grey(self, points_m: np.ndarray) -> np.ndarray:
        """Board-plane points (..., 2), metres -> grey level (...) of paper or ink; NaN off the sheet."""
        s = self.spec.square_m
        w, h = self.spec.size_m
        x, y = points_m[..., 0], points_m[..., 1]
        margin = MARGIN_SQUARES * s
        on_sheet = (x >= -margin) & (x < w + margin) & (y >= -margin) & (y < h + margin)
        on_squares = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        i = np.clip((x // s).astype(int), 0, self.spec.squares_x - 1)
        j = np.clip((y // s).astype(int), 0, self.spec.squares_y - 1)
        marker = self.marker_of_square[j, i]
        origin = self.marker_origin_m[j, i]
        cell = self.spec.marker_m / self.cells
        ci = np.floor((x - origin[..., 0]) / cell).astype(int)
        cj = np.floor((y - origin[..., 1]) / cell).astype(int)
        in_marker = (marker >= 0) & (ci >= 0) & (ci < self.cells) & (cj >= 0) & (cj < self.cells)
        marker_ink = self.marker_bits[
            np.maximum(marker, 0), np.clip(cj, 0, self.cells - 1), np.clip(ci, 0, self.cells - 1)
        ]
        ink = on_squares & (self.dark_square[j, i] | (in_marker & marker_ink))
        return np.where(on_sheet, np.where(ink, INK, PAPER), np.nan)


def corner_rays(camera: Camera) -> np.ndarray:
    """Normalised undistorted (x, y) at every pixel corner, (height + 1, width + 1, 2): the corner between
    pixels (u - 1, v - 1) and (u, v) is at (u - 0.5, v - 0.5), pixel centres being integers."""
    us = np.arange(camera.width + 1, dtype=np.float64) - 0.5
    vs = np.arange(camera.height + 1, dtype=np.float64) - 0.5
    grid = np.stack(np.meshgrid(us, vs), axis=-1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(grid, camera.K, camera.dist, criteria=_UNDISTORT_CRITERIA)
    return np.asarray(xy).reshape(camera.height + 1, camera.width + 1, 2)


def sample_offsets(supersample: int) -> list[tuple[float, float]]:
    """Where a pixel is sampled, (x, y) in [0, 1)², supersample² points: an n-rooks pattern (the regular
    n x n grid sheared by a sub-cell step in each axis), so that each axis sees supersample² distinct
    positions. On the regular grid an edge along a pixel row or column covers a pixel in steps of
    1/supersample, which moved the corners of a board lying square to the image by up to 1/(2 supersample)
    px (0.1 px biases in an oblique camera's flat view); here the step is 1/supersample²."""
    n = supersample
    return [((i + (j + 0.5) / n) / n, (j + (i + 0.5) / n) / n) for j in range(n) for i in range(n)]


def render_board(
    pattern: BoardPattern, rays: np.ndarray, T_cam_board: np.ndarray, supersample: int, light: float
) -> np.ndarray:
    """The board at pose T_cam_board (board frame -> camera frame, 4 x 4) over the table, seen through
    the camera whose `corner_rays` are `rays`: grey image (height, width) in [0, 1], noise-free.

    Points the board does not cover show the table's plain grey; the board is the only thing above
    the table, so where its sheet is hit it is in front. `light` scales the board's brightness
    (its shading towards the light)."""
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    normal = R[:, 2]
    h, w = rays.shape[0] - 1, rays.shape[1] - 1
    total = np.zeros((h, w))
    for fx, fy in sample_offsets(supersample):
        left = rays[:-1, :-1] * (1 - fy) + rays[1:, :-1] * fy
        right = rays[:-1, 1:] * (1 - fy) + rays[1:, 1:] * fy
        xy = left * (1 - fx) + right * fx
        ray = np.concatenate([xy, np.ones((h, w, 1))], axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (normal @ t) / (ray @ normal)
        hit = np.isfinite(lam) & (lam > 0)
        board_m = (np.where(hit, lam, 0.0)[..., None] * ray - t) @ R  # Rᵀ (λ ray - t), row by row
        grey = pattern.grey(board_m[..., :2])
        total += np.where(hit & ~np.isnan(grey), grey * light, TABLE)
    return total / supersample**2


def to_grey8(image: np.ndarray, sigma_grey: float, rng: np.random.Generator) -> np.ndarray:
    """[0, 1] image -> uint8: the lens's blur (a Gaussian of LENS_BLUR_PX), Gaussian sensor noise of
    sigma_grey levels of 255, then quantised."""
    blurred = cv2.GaussianBlur(image, (0, 0), LENS_BLUR_PX)
    noisy = blurred * 255.0 + rng.normal(0.0, sigma_grey, image.shape)
    return np.asarray(np.clip(np.rint(noisy), 0, 255), dtype=np.uint8)
