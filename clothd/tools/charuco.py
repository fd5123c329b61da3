"""The ChArUco board of `clothd calibrate`, and finding its corners in a picture (OpenCV's cv2.aruco).

Board frame: OpenCV's. x along a row of corner ids, y down the rows, z into the board; the board's
outer corner at (0, 0) and ChArUco corner id 0 at (square, square). OpenCV changed where it puts the
markers on boards with an even number of rows in 4.6 (its `setLegacyPattern`); this is the new layout,
the one `cv2.aruco.CharucoBoard.generateImage` prints today.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from clothd.errors import ConfigError

MIN_CORNERS = 6  # fewer corners than this say little about a view's pose


@dataclass(frozen=True)
class Board:
    """squares_x x squares_y squares of square_m, markers of marker_m from the cv2.aruco dictionary named
    `dictionary` (e.g. DICT_5X5_100). ConfigError, naming the flag, when they cannot make a board."""

    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float
    dictionary: str

    def __post_init__(self) -> None:
        if not 0 < self.marker_m < self.square_m:
            raise ConfigError(
                f"--marker-m ({self.marker_m}) must be above 0 and below --square-m ({self.square_m})"
            )
        if not (self.dictionary.startswith("DICT_") and hasattr(cv2.aruco, self.dictionary)):
            raise ConfigError(
                f"--dictionary {self.dictionary}: not a cv2.aruco dictionary (e.g. DICT_5X5_100)"
            )
        markers = self.squares_x * self.squares_y // 2
        available = len(self.cv_dictionary().bytesList)
        if markers > available:
            raise ConfigError(
                f"--dictionary {self.dictionary} holds {available} markers; the board needs {markers}"
            )

    def cv_dictionary(self) -> cv2.aruco.Dictionary:
        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        return cv2.aruco.CharucoBoard(
            (self.squares_x, self.squares_y), self.square_m, self.marker_m, self.cv_dictionary()
        )


@dataclass(frozen=True)
class Detection:
    """The ChArUco corners found in one picture: ids (n,), pixels (n, 2), board-frame points (n, 3), m."""

    ids: np.ndarray
    pixels: np.ndarray
    board_m: np.ndarray


class CornerFinder:
    """ChArUco corners of `board` in BGR or grey pictures (cv2.aruco.CharucoDetector, sub-pixel)."""

    def __init__(self, board: Board) -> None:
        self._cv_board = board.cv_board()
        charuco = cv2.aruco.CharucoParameters()
        # A corner is kept with one of its two markers found (OpenCV wants both), so the corners near the
        # picture's edge, where the lens bends most, count: over three hwsim sets the worst table-point
        # error went from 0.14-0.50 px to 0.12-0.15 px.
        charuco.minMarkers = 1
        self._detector = cv2.aruco.CharucoDetector(self._cv_board, charuco)
        self._corners_m = np.asarray(self._cv_board.getChessboardCorners(), dtype=np.float64)

    def find(self, image: np.ndarray) -> Detection | None:
        """The corners, or None when fewer than MIN_CORNERS are found or they lie on one line."""
        grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        corners, ids, _, _ = self._detector.detectBoard(grey)
        if ids is None or len(ids) < MIN_CORNERS:
            return None
        if self._cv_board.checkCharucoCornersCollinear(ids):
            return None
        ids = ids.ravel().astype(int)
        return Detection(ids, corners.reshape(-1, 2).astype(np.float64), self._corners_m[ids])
