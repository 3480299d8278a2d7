"""Front/back body map of a model pack's muscle groups, as SVG.

Each group is placed by the anatomy of its member muscles (OpenSim names such as ``DELT1`` or ``glmax2_r``): the
member names are matched against :data:`MUSCLE_RULES`, the group takes the region carrying most of its members'
strength, and its side from the members' ``_r``/``_l`` suffixes (else from the pack's coordinates, else both sides).
Groups that land on the same region and side share it in stripes. Groups whose muscles are not in the atlas are
returned in :attr:`BodyMap.unmapped` (the dashboard lists them) rather than drawn somewhere arbitrary.

The map shows only the part of the body the pack's muscles are on (:func:`extent`): the upper body (head to hands) for
an arm exercise, the lower body (hips to feet) for a leg one, else the whole figure.

Coordinates: each view is 200 x 440 units, midline at x = 100. Regions are given for the subject's right side as
(distance from the midline, height, radii, tilt); the front view shows the subject's right on the viewer's left.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from html import escape

VIEW_WIDTH, VIEW_HEIGHT, MIDLINE = 200, 440, 100


@dataclass(frozen=True)
class Region:
    view: str  # "front" or "back"
    dx: float  # centre, distance from the midline (towards the subject's side)
    cy: float
    rx: float
    ry: float
    tilt_deg: float = 0.0  # positive: top leans towards the midline
    label: str = ""


REGIONS: dict[str, Region] = {
    "deltoid_anterior": Region("front", 45, 82, 8, 13, -15, "anterior deltoid"),
    "deltoid_middle": Region("front", 55, 86, 5, 13, -10, "middle deltoid"),
    "deltoid_posterior": Region("back", 47, 82, 8, 13, -15, "posterior deltoid"),
    "pec_clavicular": Region("front", 21, 82, 15, 6, 8, "pectoralis major, clavicular"),
    "pec_sternal": Region("front", 20, 96, 16, 7, 0, "pectoralis major, sternal"),
    "pec_costal": Region("front", 19, 110, 14, 5, -5, "pectoralis major, costal"),
    "biceps_long": Region("front", 56, 118, 4.5, 20, 4, "biceps, long head"),
    "biceps_short": Region("front", 48, 120, 4.5, 19, 4, "biceps, short head"),
    "brachialis": Region("front", 57, 148, 5, 8, 4, "brachialis"),
    "brachioradialis": Region("front", 61, 178, 5, 18, 3, "brachioradialis"),
    "triceps_long": Region("back", 49, 118, 5, 21, 4, "triceps, long head"),
    "triceps_lateral": Region("back", 57, 120, 4.5, 19, 4, "triceps, lateral head"),
    "triceps_medial": Region("back", 53, 148, 5, 8, 4, "triceps, medial head"),
    "latissimus": Region("back", 28, 138, 12, 27, -12, "latissimus dorsi"),
    "erector_longissimus": Region("back", 7, 152, 4.5, 40, 0, "erector spinae, longissimus"),
    "erector_iliocostalis": Region("back", 16, 152, 4.5, 38, 0, "erector spinae, iliocostalis"),
    "multifidus": Region("back", 5, 196, 4, 11, 0, "multifidus"),
    "quadratus_lumborum": Region("back", 22, 188, 5, 9, 0, "quadratus lumborum"),
    "rectus_abdominis": Region("front", 8, 150, 7.5, 38, 0, "rectus abdominis"),
    "external_oblique": Region("front", 26, 150, 7, 22, -8, "external oblique"),
    "internal_oblique": Region("front", 23, 184, 7, 11, 20, "internal oblique"),
    "psoas": Region("front", 13, 206, 4.5, 13, -15, "psoas"),
    "tfl": Region("front", 35, 224, 5, 12, -10, "tensor fasciae latae"),
    "adductor_longus": Region("front", 10, 246, 5, 20, 10, "adductor longus"),
    "rectus_femoris": Region("front", 22, 264, 7, 30, 3, "rectus femoris"),
    "vastus_lateralis": Region("front", 32, 274, 5.5, 30, 3, "vastus lateralis"),
    "vastus_medialis": Region("front", 14, 298, 6, 15, 5, "vastus medialis / intermedius"),
    "tibialis_anterior": Region("front", 26, 366, 4.5, 30, 0, "tibialis anterior"),
    "gluteus_maximus": Region("back", 20, 228, 16, 16, 0, "gluteus maximus"),
    "gluteus_medius": Region("back", 31, 207, 10, 8, -10, "gluteus medius"),
    "biceps_femoris": Region("back", 28, 276, 6.5, 32, 3, "biceps femoris"),
    "semitendinosus": Region("back", 15, 276, 6.5, 32, 3, "semitendinosus / semimembranosus"),
    "gastroc_lateral": Region("back", 28, 350, 6, 20, 3, "gastrocnemius, lateral"),
    "gastroc_medial": Region("back", 16, 350, 6, 20, 3, "gastrocnemius, medial"),
    # the rest of a leg's muscles (gait2392 packs every right-leg muscle)
    "gluteus_minimus": Region("back", 33, 214, 7, 5, -10, "gluteus minimus"),
    "deep_hip_rotators": Region("back", 18, 243, 9, 3.5, 0, "piriformis, gemelli, quadratus femoris"),
    "adductor_magnus": Region("back", 8, 262, 5.5, 26, 5, "adductor magnus"),
    "pectineus_adductor_brevis": Region("front", 13, 226, 5, 7, 20, "pectineus, adductor brevis"),
    "gracilis": Region("front", 7, 280, 2.5, 32, 3, "gracilis"),
    "sartorius": Region("front", 20, 262, 2.5, 44, -22, "sartorius"),
    "soleus": Region("back", 22, 380, 7, 14, 0, "soleus"),
    "deep_posterior_calf": Region("back", 22, 400, 4, 7, 0, "tibialis posterior, long toe flexors"),
    "peroneals": Region("front", 32, 362, 3, 24, 0, "peroneals"),
    "toe_extensors": Region("front", 19, 372, 3, 22, 0, "long toe extensors"),
}

#: Lower-case OpenSim muscle names (side suffix removed) -> region; first match wins.
MUSCLE_RULES: tuple[tuple[str, str], ...] = (
    (r"delt1", "deltoid_anterior"),
    (r"delt2", "deltoid_middle"),
    (r"delt3", "deltoid_posterior"),
    (r"pecm1", "pec_clavicular"),
    (r"pecm2", "pec_sternal"),
    (r"pecm3", "pec_costal"),
    (r"biclong", "biceps_long"),
    (r"bicshort", "biceps_short"),
    (r"bra$", "brachialis"),
    (r"brd$", "brachioradialis"),
    (r"trilong", "triceps_long"),
    (r"trilat", "triceps_lateral"),
    (r"trimed", "triceps_medial"),
    (r"ld_|latdorsi", "latissimus"),
    (r"ltp[tl]_", "erector_longissimus"),
    (r"il_", "erector_iliocostalis"),
    (r"mf_", "multifidus"),
    (r"ql_", "quadratus_lumborum"),
    (r"rect_abd", "rectus_abdominis"),
    (r"io\d", "internal_oblique"),
    (r"e[o0]\d|e[o0]_", "external_oblique"),
    (r"psoas|ps_", "psoas"),
    (r"tfl", "tfl"),
    (r"addlong", "adductor_longus"),
    (r"recfem", "rectus_femoris"),
    (r"vaslat", "vastus_lateralis"),
    (r"vasmed|vasint", "vastus_medialis"),
    (r"tibant", "tibialis_anterior"),
    (r"glmax", "gluteus_maximus"),
    (r"glmed", "gluteus_medius"),
    (r"bf[ls]h", "biceps_femoris"),
    (r"semiten|semimem", "semitendinosus"),
    (r"gaslat", "gastroc_lateral"),
    (r"gasmed", "gastroc_medial"),
    # gait2392's names
    (r"glut_max", "gluteus_maximus"),
    (r"glut_med", "gluteus_medius"),
    (r"glut_min", "gluteus_minimus"),
    (r"quad_fem|gem$|peri$", "deep_hip_rotators"),
    (r"iliacus", "psoas"),
    (r"add_long", "adductor_longus"),
    (r"add_brev|pect$", "pectineus_adductor_brevis"),
    (r"add_mag", "adductor_magnus"),
    (r"grac$", "gracilis"),
    (r"sar$", "sartorius"),
    (r"rect_fem", "rectus_femoris"),
    (r"vas_lat", "vastus_lateralis"),
    (r"vas_med|vas_int", "vastus_medialis"),
    (r"bifem", "biceps_femoris"),
    (r"lat_gas", "gastroc_lateral"),
    (r"med_gas", "gastroc_medial"),
    (r"soleus", "soleus"),
    (r"tib_post|flex_dig|flex_hal", "deep_posterior_calf"),
    (r"tib_ant", "tibialis_anterior"),
    (r"per_", "peroneals"),
    (r"ext_dig|ext_hal", "toe_extensors"),
)
_RULES = tuple((re.compile(pattern), region) for pattern, region in MUSCLE_RULES)
_SIDE = re.compile(r"_([rl])$")


def muscle_region(name: str) -> str | None:
    bare = _SIDE.sub("", name.lower())
    for pattern, region in _RULES:
        if pattern.match(bare):
            return region
    return None


def muscle_side(name: str) -> str | None:
    """``"r"``/``"l"`` from a ``_r``/``_l`` suffix (OpenSim muscles) or an ``r_``/``l_`` prefix (arm26 coordinates)."""
    match = _SIDE.search(name.lower()) or re.match(r"^([rl])_", name.lower())
    return match.group(1) if match else None


@dataclass(frozen=True)
class Placement:
    group: str
    region: str
    side: str  # "r" or "l"


@dataclass
class BodyMap:
    pack: str
    placements: list[Placement] = field(default_factory=list)
    unmapped: list[str] = field(default_factory=list)

    def svg(
        self, *, fills: dict[str, str] | None = None, width: int | None = None, names: dict[str, str] | None = None
    ) -> str:
        return render_svg(self, fills=fills, width=width, names=names)


def place_groups(pack) -> BodyMap:
    """Where each of ``pack``'s groups goes (``pack``: a :class:`msk_core.model.ModelPack`)."""
    pack_sides = {s for s in (muscle_side(c) for c in pack.coordinates) if s}
    body = BodyMap(pack=pack.name)
    for group in pack.groups:
        members = pack.members[group]
        strength: dict[str, float] = {}
        for member in members:
            region = muscle_region(member)
            if region is not None:
                strength[region] = strength.get(region, 0.0) + float(pack.member_f_max.get(member, 1.0))
        if not strength:
            body.unmapped.append(group)
            continue
        region = max(strength, key=strength.__getitem__)
        sides = {s for s in (muscle_side(m) for m in members if muscle_region(m) == region) if s}
        if not sides and not any(muscle_side(m) for m in members):
            sides = pack_sides or {"r", "l"}
        elif not sides:
            sides = {s for s in (muscle_side(m) for m in members) if s}
        for side in sorted(sides, reverse=True):
            body.placements.append(Placement(group, region, side))
    return body


# The figure: (view-independent) ellipses (cx offset from midline, cy, rx, ry, tilt) for one side, mirrored.
_SILHOUETTE_SIDE = (
    (42, 84, 14, 16, -20),
    (53, 122, 10, 32, 5),
    (60, 185, 8, 32, 4),
    (63, 228, 7, 10, 0),  # shoulder, arm, hand
    (21, 268, 15, 50, 3),
    (23, 365, 10, 45, 0),
    (25, 420, 9, 6, 0),  # thigh, shank, foot
)


def _ellipse(cx: float, cy: float, rx: float, ry: float, tilt: float, attrs: str) -> str:
    transform = f' transform="rotate({tilt:.1f} {cx:.1f} {cy:.1f})"' if tilt else ""
    return f'<ellipse cx="{cx:.1f}" cy="{cy:.1f}" rx="{rx:.1f}" ry="{ry:.1f}"{transform} {attrs}/>'


def _x(view: str, side: str, dx: float) -> float:
    # Front view: the subject's right is on the viewer's left; back view: on the viewer's right.
    toward_viewer_left = (view == "front") == (side == "r")
    return MIDLINE - dx if toward_viewer_left else MIDLINE + dx


def _tilt(view: str, side: str, tilt: float) -> float:
    return -tilt if (view == "front") == (side == "r") else tilt


def _silhouette(offset_x: float) -> list[str]:
    body = 'class="body" fill="#e4e7eb" stroke="#c4c9d0" stroke-width="1"'
    parts = [
        f'<g transform="translate({offset_x} 0)">',
        _ellipse(MIDLINE, 34, 19, 23, 0, body),
        f'<rect x="{MIDLINE - 8}" y="52" width="16" height="16" {body}/>',
        f'<path d="M{MIDLINE - 46} 72 Q{MIDLINE} 62 {MIDLINE + 46} 72 L{MIDLINE + 36} 170 Q{MIDLINE + 42} 200 '
        f'{MIDLINE + 38} 222 L{MIDLINE - 38} 222 Q{MIDLINE - 42} 200 {MIDLINE - 36} 170 Z" {body}/>',
    ]
    for side in ("r", "l"):
        for dx, cy, rx, ry, tilt in _SILHOUETTE_SIDE:
            parts.append(
                _ellipse(MIDLINE + (dx if side == "l" else -dx), cy, rx, ry, tilt if side == "l" else -tilt, body)
            )
    parts.append("</g>")
    return parts


#: The parts of the figure a map may be limited to: (top, bottom) in view units.
UPPER_BODY = (4.0, 240.0)  # head to hands
LOWER_BODY = (186.0, VIEW_HEIGHT + 4.0)  # hips to feet
WHOLE_BODY = (4.0, VIEW_HEIGHT + 4.0)


def extent(body: BodyMap) -> tuple[float, float]:
    """(top, bottom) of the figure to draw: the upper or lower body when every placed muscle is on it, else all."""
    tops = [REGIONS[p.region].cy - REGIONS[p.region].ry for p in body.placements]
    bottoms = [REGIONS[p.region].cy + REGIONS[p.region].ry for p in body.placements]
    if not tops:
        return WHOLE_BODY
    for part in (UPPER_BODY, LOWER_BODY):
        if part[0] <= min(tops) and max(bottoms) <= part[1] - 4:
            return part
    return WHOLE_BODY


def render_svg(
    body: BodyMap, *, fills: dict[str, str] | None = None, width: int | None = None, names: dict[str, str] | None = None
) -> str:
    """Both views side by side; each muscle shape has ``class="muscle"`` and ``data-group``; ``fills`` colours them;
    its tooltip names the group and side ("Brachialis (right)") by ``names`` (display names, msk_core.model.names),
    else by its model name and region ("BRA (brachialis, right)")."""
    fills, names = fills or {}, names or {}
    # The figures span x = 30..170 of each view: the margins outside them are cut off; so is the part of the body
    # the pack has no muscle on (extent).
    left, total_w = 26, 2 * VIEW_WIDTH + 20 - 52
    top, bottom = extent(body)
    height = bottom - top
    size = f' width="{width}" height="{round(width * (height + 4) / total_w)}"' if width else ""
    part = {UPPER_BODY: "upper", LOWER_BODY: "lower"}.get((top, bottom), "whole")
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="{left} {top:g} {total_w} {height:g}"{size} '
        f'class="bodymap" data-pack="{escape(body.pack)}" data-part="{part}" role="img" '
        f'aria-label="body map of {escape(body.pack)}">',
        "<defs>",
    ]
    shared: dict[tuple[str, str], list[str]] = {}
    for p in body.placements:
        shared.setdefault((p.region, p.side), []).append(p.group)
    shapes: list[str] = []
    for (region_name, side), groups in shared.items():
        region = REGIONS[region_name]
        offset = 0 if region.view == "front" else VIEW_WIDTH + 20
        cx, tilt = _x(region.view, side, region.dx) + offset, _tilt(region.view, side, region.tilt_deg)
        for i, group in enumerate(groups):
            clip = ""
            if len(groups) > 1:  # stripes across the region, one per group
                clip_id = f"clip-{region_name}-{side}-{i}"
                x0 = cx - region.rx - 1 + i * (2 * region.rx + 2) / len(groups)
                out.append(
                    f'<clipPath id="{clip_id}"><rect x="{x0:.1f}" y="{region.cy - region.ry - 20:.1f}" '
                    f'width="{(2 * region.rx + 2) / len(groups):.2f}" height="{2 * region.ry + 40:.1f}"/></clipPath>'
                )
                clip = f' clip-path="url(#{clip_id})"'
            fill = fills.get(group, "#b8bec7")
            attrs = (
                f'class="muscle" data-group="{escape(group)}" data-side="{side}" fill="{fill}" stroke="#5b6470" '
                f'stroke-width="0.8"{clip}'
            )
            side_word = "right" if side == "r" else "left"
            title = f"{names[group]} ({side_word})" if group in names else f"{group} ({region.label}, {side_word})"
            shapes.append(
                f"<g><title>{escape(title)}</title>"
                + _ellipse(cx, region.cy, region.rx, region.ry, tilt, attrs)
                + "</g>"
            )
    # the drawing clipped to the part shown: a page that gives the map a taller box than the part's (the viewBox is
    # fitted, centred, and the rest of the box drawn too) showed the legs under an arm exercise (found by a new user)
    view_clip = f"part-{escape(body.pack)}-{part}"
    out.append(
        f'<clipPath id="{view_clip}"><rect x="{left}" y="{top:g}" width="{total_w}" height="{height:g}"/></clipPath>'
    )
    out.append("</defs>")
    out.append(f'<g clip-path="url(#{view_clip})">')
    out += _silhouette(0) + _silhouette(VIEW_WIDTH + 20)
    out += shapes
    out.append("</g>")
    # each view named in its top left corner, beside the head (nothing is drawn there)
    text = 'font-family="sans-serif" font-size="15" fill="#1d2630"'
    out.append(f'<text x="{MIDLINE - 68}" y="{top + 16:g}" {text}>front</text>')
    out.append(f'<text x="{VIEW_WIDTH + 20 + MIDLINE - 68}" y="{top + 16:g}" {text}>back</text>')
    out.append("</svg>")
    return "\n".join(out)


#: The activation colour scale: saturated yellow (0) -> orange (25 %) -> red -> dark red (100 %), so that low
#: activations stand out from the grey body (#e4e7eb, CIE76 colour difference > 75 over 0-25 %, where the former pale
#: yellow #fff5c8 at 0 % was 26). The page's copy: static/dashboard.js STOPS.
COLOUR_STOPS = (
    (0.0, (255, 222, 60)),
    (0.25, (253, 160, 40)),
    (0.5, (234, 85, 35)),
    (0.75, (180, 20, 30)),
    (1.0, (100, 0, 20)),
)


def activation_colour(value: float | None) -> str:
    """Grey for unknown, else yellow (0) -> orange -> dark red (1): one scale for the page and the report."""
    if value is None or value != value:
        return "#b8bec7"
    v = min(max(float(value), 0.0), 1.0)
    stops = COLOUR_STOPS
    for (v0, c0), (v1, c1) in zip(stops, stops[1:]):
        if v <= v1:
            f = (v - v0) / (v1 - v0)
            r, g, b = (round(a + (b - a) * f) for a, b in zip(c0, c1))
            return f"#{r:02x}{g:02x}{b:02x}"
    return "#640014"
