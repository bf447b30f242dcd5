/* One bounce of the gather, E(p) += sum_i w_i(p) L(S_i[p]), for one batch of directions.
 *
 * The numpy twin is core.transport.gather; every step below mirrors it in float32
 * so the two agree to float32 rounding. One invocation per sample; samples are laid
 * out row-major in a 2D grid (sample_width wide).
 *
 * hit_object  (batch layers) R32F: object index, or -1 miss, -2 below horizon, -3 backface
 * hit_uv      (batch layers) RG32F: atlas coordinate of the hit; on a vertex-mode object
 *             embree's barycentrics (u, v) in the hit triangle
 * hit_triangle (batch layers) R32F: the hit triangle within its object (exact integer);
 *             read on vertex-mode objects only (a 1 x 1 dummy without them)
 * normals     RGBA32F: shading normal xyz, gather normalisation in w
 * radiance    (channel layers) RGBA32F: every object's padded atlas, flattened row-major
 *             into a radiance_width wide image (flat index f at (f % width, f / width))
 * objects     RGBA32F, one column per object: row 0 width, height, offset / 4096,
 *             offset % 4096; row 1 vertex mode (1 or 0), corner_base / 4096,
 *             corner_base % 4096, unused
 * corners     RGBA32F: row r of the layout's corner table (the flat indices of a vertex
 *             triangle's three samples) in texels 2r and 2r + 1 of a corner_width wide
 *             image (texel t at (t % width, t / width)): f0 / 4096, f0 % 4096, f1 / 4096,
 *             f1 % 4096 and f2 / 4096, f2 % 4096, unused, unused
 * directions  RGBA32F, one column per direction: row 0 the direction, rows 1.. the
 *             world radiance per channel layer
 * excluded    (ceil(objects / 64) layers) RGBA32F: per sample, 16 objects per channel
 *             as an exact integer bit mask (objects this sample must not gather)
 * accumulated (channel layers) RGBA32F image, read and written
 */

vec4 fetch_radiance(int flat_index, int layer)
{
  return texelFetch(radiance, ivec3(flat_index % radiance_width, flat_index / radiance_width, layer), 0);
}

int split_index(float high, float low)
{
  return int(high) * 4096 + int(low);
}

bool is_excluded(ivec2 cell, int object_index)
{
  vec4 masks = texelFetch(excluded, ivec3(cell, object_index / 64), 0);
  int channel = (object_index % 64) / 16;
  uint bits = uint(masks[channel]);
  return ((bits >> uint(object_index % 16)) & 1u) != 0u;
}

void main()
{
  ivec2 cell = ivec2(gl_GlobalInvocationID.xy);
  int sample_index = cell.y * sample_width + cell.x;
  if (cell.x >= sample_width || sample_index >= sample_count) {
    return;
  }
  vec4 normal_scale = texelFetch(normals, cell, 0);
  vec3 normal = normal_scale.xyz;
  float scale = normal_scale.w;
  vec4 sums[12]; /* MAX_CHANNEL_LAYERS in gather.py */
  for (int layer = 0; layer < channel_layers; layer++) {
    sums[layer] = vec4(0.0);
  }
  for (int j = 0; j < batch_count; j++) {
    int direction_index = batch_start + j;
    vec3 direction = texelFetch(directions, ivec2(direction_index, 0), 0).xyz;
    float weight = max(dot(normal, direction), 0.0) * scale;
    float code = texelFetch(hit_object, ivec3(cell, j), 0).r;
    if (weight <= 0.0 || code < -1.5) {
      continue; /* below the horizon, a backface, or no weight */
    }
    if (code < -0.5) {
      if (has_world != 0) {
        for (int layer = 0; layer < channel_layers; layer++) {
          sums[layer] += weight * texelFetch(directions, ivec2(direction_index, 1 + layer), 0);
        }
      }
      continue;
    }
    int object_index = int(code + 0.5);
    if (use_exclude != 0 && is_excluded(cell, object_index)) {
      continue;
    }
    vec2 uv = texelFetch(hit_uv, ivec3(cell, j), 0).xy;
    if (has_vertex != 0) {
      vec4 vertex_meta = texelFetch(objects, ivec2(object_index, 1), 0);
      if (vertex_meta.x > 0.5) {
        /* AtlasLayout.vertex_lookup: the hit triangle's three samples mixed by the
         * barycentrics, w0 = (1 - u) - v, or the corner of the largest weight only. */
        int triangle = int(texelFetch(hit_triangle, ivec3(cell, j), 0).r);
        int row = split_index(vertex_meta.y, vertex_meta.z) + triangle;
        int texel = 2 * row;
        vec4 first = texelFetch(corners, ivec2(texel % corner_width, texel / corner_width), 0);
        texel += 1;
        vec4 second = texelFetch(corners, ivec2(texel % corner_width, texel / corner_width), 0);
        int f0 = split_index(first.x, first.y);
        int f1 = split_index(first.z, first.w);
        int f2 = split_index(second.x, second.y);
        float w0 = 1.0 - uv.x - uv.y;
        float w1 = uv.x;
        float w2 = uv.y;
        if (nearest_vertex != 0) {
          /* np.argmax: the first of equal largest weights */
          int chosen = (w0 >= w1 && w0 >= w2) ? f0 : ((w1 >= w2) ? f1 : f2);
          for (int layer = 0; layer < channel_layers; layer++) {
            sums[layer] += weight * fetch_radiance(chosen, layer);
          }
        }
        else {
          for (int layer = 0; layer < channel_layers; layer++) {
            vec4 mixed = fetch_radiance(f0, layer) * w0 + fetch_radiance(f1, layer) * w1;
            mixed = mixed + fetch_radiance(f2, layer) * w2;
            sums[layer] += weight * mixed;
          }
        }
        continue;
      }
    }
    vec4 meta = texelFetch(objects, ivec2(object_index, 0), 0);
    float width = meta.x;
    float height = meta.y;
    int offset = split_index(meta.z, meta.w);
    float x = min(max(uv.x * width - 0.5, 0.0), width - 1.0);
    float y = min(max(uv.y * height - 0.5, 0.0), height - 1.0);
    int x0 = int(x);
    int y0 = int(y);
    float fx = x - float(x0);
    float fy = y - float(y0);
    int stride = int(width) + 1;
    int base = offset + y0 * stride + x0;
    for (int layer = 0; layer < channel_layers; layer++) {
      vec4 c00 = fetch_radiance(base, layer);
      vec4 c01 = fetch_radiance(base + 1, layer);
      vec4 c10 = fetch_radiance(base + stride, layer);
      vec4 c11 = fetch_radiance(base + stride + 1, layer);
      vec4 bottom = c00 + (c01 - c00) * fx;
      vec4 top = c10 + (c11 - c10) * fx;
      sums[layer] += weight * (bottom + (top - bottom) * fy);
    }
  }
  for (int layer = 0; layer < channel_layers; layer++) {
    ivec3 at = ivec3(cell, layer);
    imageStore(accumulated, at, imageLoad(accumulated, at) + sums[layer]);
  }
}
