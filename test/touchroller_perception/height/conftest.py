"""A small three-light Lambertian renderer of ball presses, written here (it shares nothing with the
simulator): uneven light across the image, a sphere cap pressed into a flat membrane."""
from __future__ import annotations

import numpy as np
import pytest

PIXEL = 5e-5          # m per pixel
BALL = 2.0e-3         # m
SHAPE = (120, 160)


def cap_slopes(shape, cu, cv, contact_px, pixel=PIXEL, ball=BALL, skirt=0.3):
    """Slopes and indentation (m, 0 far away) of a ball pressed in with the gel sinking around it: inside
    the contact the sphere; outside a skirt whose slope decays as exp(-(rho - a) / (skirt a)), matched
    to the sphere's slope at the edge a (continuous height and slope)."""
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    dx, dy = (uu - cu) * pixel, (vv - cv) * pixel
    rho = np.hypot(dx, dy)
    a = contact_px * pixel
    inside = rho < a
    s = np.sqrt(np.maximum(ball**2 - rho**2, 1e-12))
    edge_slope = a / np.sqrt(ball**2 - a**2)                # |dz/drho| at the edge
    length = skirt * a
    radial = np.where(inside, rho / s, edge_slope * np.exp(-(rho - a) / length))
    with np.errstate(invalid="ignore", divide="ignore"):
        ux, uy = np.where(rho > 0, dx / rho, 0.0), np.where(rho > 0, dy / rho, 0.0)
    gx, gy = -radial * ux, -radial * uy
    sink = edge_slope * length * (1 - np.exp(-(rho - a) / length))
    z_edge = edge_slope * length                             # the rim's indentation (the far field is 0)
    z = np.where(inside, np.sqrt(np.maximum(ball**2 - rho**2, 0)) - np.sqrt(ball**2 - a**2) + z_edge,
                 z_edge - sink)
    return gx, gy, z


def shade(gx, gy):
    h, w = gx.shape
    vv, uu = np.mgrid[0:h, 0:w]
    light = 0.8 + 0.4 * uu / w - 0.15 * vv / h            # uneven illumination
    n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    el = np.radians(35.0)
    channels = []
    for az in (0.0, 120.0, 240.0):
        a = np.radians(az)
        lvec = np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)])
        channels.append(40 + 150 * light * np.clip(n @ lvec, 0, None))
    return np.clip(np.stack(channels, -1), 0, 255)


def press_image(cu, cv, contact_px, rng=None):
    gx, gy, z = cap_slopes(SHAPE, cu, cv, contact_px)
    img = shade(gx, gy)
    if rng is not None:
        img = img + rng.normal(0, 0.8, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), gx, gy, z


@pytest.fixture(scope="session")
def synthetic_presses():
    rng = np.random.default_rng(3)
    presses = []
    for _ in range(12):
        cu, cv = rng.uniform(45, 115), rng.uniform(40, 80)
        contact = rng.uniform(16, 22)
        img, gx, gy, z = press_image(cu, cv, contact, rng)
        presses.append((img, cu, cv, contact, gx, gy, z))
    reference = np.clip(np.rint(shade(np.zeros(SHAPE), np.zeros(SHAPE))), 0, 255).astype(np.uint8)
    return reference, presses
