"""Pure-numpy rendering of Quadcopter-v0: a top view and a side view side by side.

Points are drawn in pixel coordinates ``(column, row)``, as float arrays of shape
``(K, 2)``; images are uint8 arrays of shape ``(height, width, 3)``.
"""

from collections.abc import Sequence

import numpy as np

from cme_agent.envs.quadcopter_dynamics import rotation_matrix

Color = tuple[int, int, int]

BACKGROUND: Color = (250, 250, 250)
BOX: Color = (170, 170, 170)
GROUND: Color = (150, 110, 70)
TARGET: Color = (40, 160, 70)
TRAIL: Color = (80, 120, 220)
CRAFT: Color = (30, 30, 30)
NOSE: Color = (220, 40, 40)
ARM_LENGTH = 0.3  # m, drawn at least MIN_ARM_PIXELS long
MIN_ARM_PIXELS = 8.0
PADDING = 10  # pixels around each view


def stamp(image: np.ndarray, points: np.ndarray, color: Color, width: int = 1) -> None:
    """Paint square dots of side ``width`` centred on points; those off the image are skipped.

    :param image: the image, shape ``(H, W, 3)``, modified in place.
    :param points: pixel coordinates ``(column, row)``, shape ``(K, 2)``.
    :param color: RGB colour.
    :param width: side of each dot (pixels).
    """
    centres = np.rint(points).astype(np.int64)
    offsets = np.arange(width) - width // 2
    columns = (centres[:, None, None, 0] + offsets[None, :, None]).ravel()
    rows = (centres[:, None, None, 1] + offsets[None, None, :]).ravel()
    inside = (columns >= 0) & (columns < image.shape[1]) & (rows >= 0) & (rows < image.shape[0])
    image[rows[inside], columns[inside]] = color


def draw_polyline(image: np.ndarray, points: np.ndarray, color: Color, width: int = 1) -> None:
    """Draw segments joining consecutive points, sampled at least once per pixel.

    :param image: the image, shape ``(H, W, 3)``, modified in place.
    :param points: vertices in pixel coordinates ``(column, row)``, shape ``(K, 2)``.
    :param color: RGB colour.
    :param width: line width (pixels).
    """
    starts, steps = points[:-1], np.diff(points, axis=0)
    counts = np.ceil(np.abs(steps).max(axis=1, initial=0.0)).astype(np.int64) + 1
    segment = np.repeat(np.arange(len(steps)), counts)
    first_sample = np.repeat(np.cumsum(counts) - counts, counts)
    fraction = (np.arange(counts.sum()) - first_sample) / np.repeat(np.maximum(counts - 1, 1), counts)
    stamp(image, starts[segment] + fraction[:, None] * steps[segment], color, width)


def fill_disc(image: np.ndarray, centre: np.ndarray, radius: float, color: Color) -> None:
    """Fill a disc.

    :param image: the image, shape ``(H, W, 3)``, modified in place.
    :param centre: pixel coordinates ``(column, row)``, shape ``(2,)``.
    :param radius: radius (pixels).
    :param color: RGB colour.
    """
    top, bottom = max(int(centre[1] - radius), 0), min(int(centre[1] + radius) + 2, image.shape[0])
    left, right = max(int(centre[0] - radius), 0), min(int(centre[0] + radius) + 2, image.shape[1])
    rows, columns = np.ogrid[top:bottom, left:right]
    inside = (columns - centre[0]) ** 2 + (rows - centre[1]) ** 2 <= radius**2
    image[top:bottom, left:right][inside] = color


def draw_circle(image: np.ndarray, centre: np.ndarray, radius: float, color: Color) -> None:
    """Draw the outline of a circle.

    :param image: the image, shape ``(H, W, 3)``, modified in place.
    :param centre: pixel coordinates ``(column, row)``, shape ``(2,)``.
    :param radius: radius (pixels).
    :param color: RGB colour.
    """
    angles = np.linspace(0.0, 2.0 * np.pi, max(int(2.0 * np.pi * radius), 8) + 1)
    draw_polyline(image, centre + radius * np.stack([np.cos(angles), np.sin(angles)], 1), color)


class View:
    """An orthographic view of NED space onto a square panel, in the panel's pixels.

    :param size: side of the panel (pixels).
    :param axes: NED axes ``(horizontal, vertical)`` shown, 0 = north, 1 = east, 2 = down.
    :param signs: sign of each shown axis (+1 or -1; -1 on axis 2 shows altitude).
    :param low: lower corner of the region shown in NED (m), shape ``(3,)``.
    :param high: upper corner of the region shown in NED (m), shape ``(3,)``.
    """

    def __init__(
        self,
        size: int,
        axes: tuple[int, int],
        signs: tuple[float, float],
        low: np.ndarray,
        high: np.ndarray,
    ) -> None:
        self.axes, self.signs = list(axes), np.array(signs)
        corners = np.stack([low[self.axes], high[self.axes]]) * self.signs
        self.minimum, maximum = corners.min(axis=0), corners.max(axis=0)
        self.scale = (size - 2 * PADDING) / (maximum - self.minimum).max()  # pixels per m
        margin = (size - self.scale * (maximum - self.minimum)) / 2.0
        self.origin = np.array([margin[0], size - margin[1]])

    def pixels(self, points: np.ndarray) -> np.ndarray:
        """Project NED points (m), shape ``(K, 3)``, to pixels ``(column, row)``, ``(K, 2)``."""
        plane = (points[:, self.axes] * self.signs - self.minimum) * self.scale
        return self.origin + plane * np.array([1.0, -1.0])

    def rectangle(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Outline of the box ``[low, high]`` (NED, m, shape ``(3,)``): 5 pixels ``(5, 2)``."""
        corners = np.tile(low, (5, 1))
        horizontal, vertical = self.axes
        corners[[1, 2], horizontal] = high[horizontal]
        corners[[2, 3], vertical] = high[vertical]
        return self.pixels(corners)


def _draw_view(
    image: np.ndarray,
    view: View,
    trail: np.ndarray,
    attitude: Sequence[float],
    target: np.ndarray,
    sigma: float,
    low: np.ndarray,
    high: np.ndarray,
) -> None:
    """Draw the box, the target, the trail and the craft on one view's panel (see render_frame)."""
    draw_polyline(image, view.rectangle(low, high), BOX)
    centre = view.pixels(target[None])[0]
    draw_circle(image, centre, sigma * view.scale, TARGET)
    fill_disc(image, centre, 4.0, TARGET)
    if len(trail) > 1:
        draw_polyline(image, view.pixels(trail), TRAIL)
    arm = max(ARM_LENGTH, MIN_ARM_PIXELS / view.scale)
    position = trail[-1]
    body_axes = rotation_matrix(*attitude)  # rows: body x (nose), y, z axes in NED
    for axis, sign, color in ((0, 1.0, NOSE), (0, -1.0, CRAFT), (1, 1.0, CRAFT), (1, -1.0, CRAFT)):
        tip = position + sign * arm * body_axes[axis]
        draw_polyline(image, view.pixels(np.stack([position, tip])), color, width=2)
    fill_disc(image, view.pixels(position[None])[0], 2.5, CRAFT)


def render_frame(
    trail: np.ndarray,
    attitude: Sequence[float],
    target: np.ndarray,
    sigma: float,
    low: np.ndarray,
    high: np.ndarray,
    height: int,
) -> np.ndarray:
    """Top view (north up, east right) and side view (north right, altitude up).

    Each view shows the bounding box (grey), the target with a circle of radius ``sigma``
    (green), the trail (blue) and the craft's arms (nose in red); the side view also
    shows the ground (brown).

    :param trail: positions visited this episode in NED (m), shape ``(T, 3)``; the last
        one is the craft's.
    :param attitude: roll, pitch, yaw of the craft (rad), shape ``(3,)``.
    :param target: target position in NED (m), shape ``(3,)``.
    :param sigma: reward width (m).
    :param low: lower corner of the bounding box in NED (m), shape ``(3,)``.
    :param high: upper corner of the bounding box in NED (m), shape ``(3,)``.
    :param height: image height (pixels).
    :return: the image, uint8, shape ``(height, 2 * height, 3)``.
    """
    image = np.full((height, 2 * height, 3), BACKGROUND, dtype=np.uint8)
    above_ground = high.copy()  # the side view shows the ground even if the box ends higher
    above_ground[2] = max(high[2], 0.0)
    top_panel, side_panel = image[:, :height], image[:, height:]  # views into image
    top = View(height, (1, 0), (1.0, 1.0), low, high)
    side = View(height, (0, 2), (1.0, -1.0), low, above_ground)
    ground = np.array([[low[0], 0.0, 0.0], [high[0], 0.0, 0.0]])
    draw_polyline(side_panel, side.pixels(ground), GROUND, width=2)
    for panel, view in ((top_panel, top), (side_panel, side)):
        _draw_view(panel, view, trail, attitude, target, sigma, low, high)
    image[:, height - 1 : height + 1] = BOX
    return image
