/* The world where no surface is: the equirectangular image looked up bilinearly along the
 * fragment's ray, periodic in both axes (Cycles' Environment Texture, as
 * core.lightfield.scene.world_lookup). ndc_to_direction maps (ndc x, ndc y, 1) to the ray's
 * world direction; pixel_to_ndc = (2 / columns, 2 / rows, -1, -1). */
#define LF_PI 3.14159265358979323846
void main()
{
  vec2 ndc = gl_FragCoord.xy * pixel_to_ndc.xy + pixel_to_ndc.zw;
  vec3 d = ndc_to_direction * vec3(ndc, 1.0);
  float u = 0.5 - atan(d.y, d.x) / (2.0 * LF_PI);
  float v = 1.0 - acos(clamp(d.z / length(d), -1.0, 1.0)) / LF_PI;
  ivec2 size = textureSize(world, 0);
  vec2 p = vec2(u, v) * vec2(size) - 0.5;
  vec2 cell = floor(p);
  vec2 t = p - cell;
  /* Wrap in float: llvmpipe runs integer division one lane at a time. cell is within a texel
   * of [0, size), so one step of floor() puts it in [0, size) exactly. */
  vec2 fsize = vec2(size);
  cell -= fsize * floor(cell / fsize);
  ivec2 a = min(ivec2(cell), size - 1);
  ivec2 b = ivec2(mix(cell + 1.0, vec2(0.0), greaterThanEqual(cell + 1.0, fsize)));
  vec3 bottom = texelFetch(world, ivec2(a.x, a.y), 0).rgb * (1.0 - t.x) +
                texelFetch(world, ivec2(b.x, a.y), 0).rgb * t.x;
  vec3 top = texelFetch(world, ivec2(a.x, b.y), 0).rgb * (1.0 - t.x) +
             texelFetch(world, ivec2(b.x, b.y), 0).rgb * t.x;
  color = vec4(bottom * (1.0 - t.y) + top * t.y, 1.0);
#ifdef WANT_DEPTH
  depth = 0.0; /* no surface: read back as inf */
#endif
}
