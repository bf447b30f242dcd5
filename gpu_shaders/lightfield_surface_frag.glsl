/* A surface's radiance: the lighting image's bilinear sample at the interpolated UV
 * (clamp-to-edge, texel centres at (i + 0.5) / size: core.lightfield.scene.sample_bilinear_clamp)
 * plus the interpolated per-corner radiance. With WANT_DEPTH, also the depth along the optical
 * axis: clip w, which 1 / gl_FragCoord.w holds. */
void main()
{
  vec3 value = vec3(0.0);
#ifdef TEXTURED
  ivec2 size = textureSize(lighting, 0);
  vec2 p = v_uv * vec2(size) - 0.5;
  vec2 cell = floor(p);
  vec2 t = p - cell;
  /* Clamp the float first: a huge UV must not overflow the integer. */
  ivec2 lo = ivec2(clamp(cell, vec2(-1.0), vec2(size)));
  ivec2 a = clamp(lo, ivec2(0), size - 1);
  ivec2 b = clamp(lo + 1, ivec2(0), size - 1);
  vec3 bottom = texelFetch(lighting, ivec2(a.x, a.y), 0).rgb * (1.0 - t.x) +
                texelFetch(lighting, ivec2(b.x, a.y), 0).rgb * t.x;
  vec3 top = texelFetch(lighting, ivec2(a.x, b.y), 0).rgb * (1.0 - t.x) +
             texelFetch(lighting, ivec2(b.x, b.y), 0).rgb * t.x;
  value = bottom * (1.0 - t.y) + top * t.y;
#endif
  color = vec4(value + v_radiance, 1.0);
#ifdef WANT_DEPTH
  depth = 1.0 / gl_FragCoord.w;
#endif
}
