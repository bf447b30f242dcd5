"""Every tolerance and epsilon of the core, in one place.

Each value says why it has the size it has; change them here, never inline.
"""

# Ray origin offset (Waechter & Binder, Ray Tracing Gems ch. 6): below ORIGIN_SCALE
# the float grid is too fine for an integer-ULP step to help, so a tiny absolute
# step along the normal is used instead.
RAY_OFFSET_ORIGIN = 1.0 / 32.0
RAY_OFFSET_FLOAT_SCALE = 1.0 / 65536.0
RAY_OFFSET_INT_SCALE = 256.0

# Shadow rays to a point light stop this fraction short of the light, so geometry
# that touches the light's position is not counted twice.
SHADOW_RAY_SHORTEN = 1e-4

# A triangle whose doubled area (|cross|) is below this, relative to the square of
# its longest edge, has no usable normal: it is skipped rather than shaded.
DEGENERATE_TRIANGLE_RATIO = 1e-12

# A face whose corner normals all agree with its own normal to this (1 - cos) is flat-shaded:
# float32 normals of a flat face differ from the float64 face normal by ~1e-7.
FLAT_NORMAL_SLACK = 1e-5

# Barycentric slack when deciding whether a texel centre lies inside a UV triangle.
RASTER_EDGE_EPSILON = 1e-7

# Below this the sum of a sample's gather weights is treated as "no open direction".
MIN_WEIGHT_SUM = 1e-12

# Sample points are kept this far (in barycentric terms) inside their triangle. A
# texel centre on, or a hair outside, a chart edge otherwise sits on the plane of the
# adjacent face (a floor meeting a wall) and its rays hit that face at t ~ 0.
SAMPLE_BARYCENTRIC_INSET = 1e-4

# An emissive object is sampled directly (next-event estimation) from samples that
# see it under fewer than this many direction cells (4*pi/N each); there the fixed
# directions would show it as blobs ("ray effects"). Larger emitters are gathered.
EMITTER_DIRECT_CELLS = 8.0

# A UV coordinate this far outside [0, 1] is still "inside": float32 UVs written at
# exactly 0 or 1 may come back a few ULPs off after a round trip through Blender.
UV_RANGE_SLACK = 1e-6

# xatlas tests degeneracy with absolute thresholds (face area <= FLT_EPSILON,
# welding distance FLT_EPSILON), so meshes are rescaled to a median edge length of
# 1 before unwrapping; a triangle whose doubled area is below this (in those units)
# would be ignored by xatlas and is dropped up front instead.
UNWRAP_MIN_DOUBLED_AREA = 8.0 * 1.1920929e-07  # 8 float32 epsilons

# xatlas's test is |dot - 1| <= 1e-4; ours is a little looser so that float32 rounding of
# the normals cannot hide a chain xatlas would follow.
PLANAR_CHAIN_DOT_SLACK = 1.05e-4

# Texel spans are widened by this (in texels) before the exact test, so rounding
# in the span computation can never drop a centre the test would accept.
SPAN_MARGIN = 1e-6

# Lamp strengths above this are refused: their irradiance times an albedo would
# overflow the float32 outputs (3.4e38) after the inverse-square factor of a texel
# a millimetre from the lamp.
MAX_LIGHT_STRENGTH = 1e30

# Environment cells: a pixel's nearest direction found within the polar band is only
# trusted if its dot product beats the band's edge by this much, so float64 rounding
# of the dot products cannot hide a nearer direction just outside the band.
ENV_NEAREST_DOT_SLACK = 1e-9

# The bounding sphere of a changed object is enlarged by this (relative to its radius
# and to its distance from the origin, where float32 rays lose precision) before rays
# that miss it are ruled out of an incremental table update: a ray it wrongly rules
# out would keep a stale entry, one it wrongly keeps only costs a trace.
CULL_SPHERE_MARGIN = 1e-3

# Corner normals of one vertex closer than this (per component, unit vectors) are one
# normal: smooth shading stores the same normal at every corner up to float32 rounding
# (~1e-7), while a sharp edge splits them by far more.
SPLIT_NORMAL_TOLERANCE = 1e-4

# Vertex samples move this far (times max(1, |position|), as in Cycles' vertex-colour
# bake) towards the middle of their triangles, off the surfaces of objects that touch
# them; small enough to change nothing a texel-free point sample could show.
VERTEX_SAMPLE_INSET = 1e-4

# A vertex-mode triangle is reported as too coarse when the direct light at its middle
# differs from its corners' mean by more than this share of the larger: a shadow edge
# or a highlight inside it, which interpolation between vertices cannot show. Light
# below TESSELLATION_FLOOR of the object's brightest is not judged (dark regions'
# relative differences are noise).
TESSELLATION_DIFFERENCE = 0.25
TESSELLATION_FLOOR = 1e-3
