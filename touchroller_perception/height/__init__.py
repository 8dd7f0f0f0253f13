"""Height from a GelSight-type image: slopes from colour (`photometric`), slopes to metres (`integrate`).

The membrane is lit by three coloured lights from different directions, so each pixel's colour change
against the no-contact reference encodes the membrane's slope (dz/dx, dz/dy); `photometric` learns that
map from presses of a ball of known radius, and `integrate` turns slopes into height with an exact
least-squares Poisson solver. `band` applies both to one image (a whole frame or the roller's contact
band): the per-frame height the CLI writes and a world mapper can place. Nothing here imports rclpy.
"""
from touchroller_perception.height.integrate import divergence, forward_differences, integrate, poisson_solve

__all__ = ["divergence", "forward_differences", "integrate", "poisson_solve"]
