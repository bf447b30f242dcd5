/* One slice of the volume slice sweep: the twin of one iteration of the slice loop of
 * core.kernels.volume_kernels.sweep_transmittance (the paper's section 6.1).
 *
 * Every voxel of slice `slice_index` continues the value the previous slice carries, read
 * bilinearly where its ray towards the lamp crosses that slice, over the segment between
 * (trapezoidal in density). A sun carries the transmittance, a lamp at a position the mean
 * extinction along the ray to it. Slices depend on the one before, so the sweep is one
 * dispatch per slice (the dispatch is the global synchronisation); the carried values
 * ping-pong between two 2D images. Every step follows the kernel's arithmetic in float32.
 *
 * The sweep runs in the kernel's frame: axis a (along the sweep, increasing away from the
 * lamp), b (rows) and c (columns); index-space vectors go to world vectors through
 * `linear_row_x/y/z` (the rows of the frame's linear map).
 *
 * density           (A + 3 layers) R32F, (C + 3) x (B + 3): the padded, permuted (not
 *                   flipped) density, layer a', row b', column c' = density[a', b', c']
 * previous_carried  R32F, C x B: what the previous slice carries at its voxels (the
 *                   kernel's padded border is not stored: it is `outside` everywhere)
 * next_carried      R32F image, C x B: this slice's carried values
 * transmittance_atlas R32F image: this slice's results in the C x B tile at tile_origin;
 *                   UNSELECTED where the voxel is outside the selection box
 * select_box        the rows (x..y) and columns (z..w), inclusive, this slice writes:
 *                   the lamp's pyramid, evaluated on the CPU in float64 as the kernel does
 *                   (volume_sweep.py says why)
 * lamp_within_slice 1 when the lamp lies within one slice (the kernel's a - light[0] <= 1,
 *                   evaluated on the CPU in float64): integrate straight to the lamp
 *
 * Dispatch: x over columns c, y over rows b, 16 x 16 a group.
 */

/* What a voxel outside the selection writes to the atlas: never a transmittance. */
#define UNSELECTED -1.0

float density_at(int layer, int row, int column)
{
  return texelFetch(density, ivec3(column, row, layer), 0).r;
}

/* Padded slice `layer` of the density at in-slice index point (b, c); 0 beyond [-1, n] on
 * either axis (the kernel's _bilinear_slice with outside = 0). */
float density_bilinear(int layer, float b, float c)
{
  ivec3 size = textureSize(density, 0);
  float pb = b + 1.0;
  float pc = c + 1.0;
  if (pb < 0.0 || pc < 0.0 || pb > float(size.y - 2) || pc > float(size.x - 2)) {
    return 0.0;
  }
  int j = int(pb);
  int m = int(pc);
  float fb = pb - float(j);
  float fc = pc - float(m);
  float low = density_at(layer, j, m) + (density_at(layer, j + 1, m) - density_at(layer, j, m)) * fb;
  float high = density_at(layer, j, m + 1) +
               (density_at(layer, j + 1, m + 1) - density_at(layer, j, m + 1)) * fb;
  return low + (high - low) * fc;
}

/* The previous slice's carried value at the kernel's padded in-slice index (j, m): its
 * border (index 0 and n + 1, n + 2), which the kernel never writes, holds `outside`. */
float previous_at(int j, int m, float outside)
{
  ivec2 size = textureSize(previous_carried, 0);
  if (j < 1 || m < 1 || j > size.y || m > size.x) {
    return outside;
  }
  return texelFetch(previous_carried, ivec2(m - 1, j - 1), 0).r;
}

/* The kernel's bilinear read of `previous` at in-slice index point (b, c). */
float previous_bilinear(float b, float c, float outside)
{
  ivec2 size = textureSize(previous_carried, 0);
  float pb = b + 1.0;
  float pc = c + 1.0;
  if (!(pb >= 0.0 && pc >= 0.0 && pb <= float(size.y + 1) && pc <= float(size.x + 1))) {
    return outside;
  }
  int j = int(pb);
  int m = int(pc);
  float fb = pb - float(j);
  float fc = pc - float(m);
  float low = previous_at(j, m, outside) + (previous_at(j + 1, m, outside) - previous_at(j, m, outside)) * fb;
  float high = previous_at(j, m + 1, outside) +
               (previous_at(j + 1, m + 1, outside) - previous_at(j, m + 1, outside)) * fb;
  return low + (high - low) * fc;
}

/* The world length of the frame's index-space vector (sa, sb, sc), summed as the kernel does. */
float world_length(float sa, float sb, float sc)
{
  float wx = linear_row_x.x * sa + linear_row_x.y * sb + linear_row_x.z * sc;
  float wy = linear_row_y.x * sa + linear_row_y.y * sb + linear_row_y.z * sc;
  float wz = linear_row_z.x * sa + linear_row_z.y * sb + linear_row_z.z * sc;
  return sqrt(wx * wx + wy * wy + wz * wz);
}

void finish(ivec2 cell, float carried, float value, bool selected)
{
  imageStore(next_carried, cell, vec4(carried));
  imageStore(transmittance_atlas, tile_origin + cell, vec4(selected ? value : UNSELECTED));
}

void main()
{
  ivec2 cell = ivec2(gl_GlobalInvocationID.xy);
  ivec2 size = imageSize(next_carried);
  if (cell.x >= size.x || cell.y >= size.y) {
    return;
  }
  int b = cell.y;
  int c = cell.x;
  int a = slice_index;
  int count_a = textureSize(density, 0).z - 3;
  bool point = is_point != 0;
  /* Outside the grid nothing attenuates: transmittance 1 (a sun), mean extinction 0 (a lamp). */
  float outside = point ? 0.0 : 1.0;
  /* Padded layers of this slice and the one behind it (the kernel's slice_here, slice_behind). */
  int slice_here = flip != 0 ? count_a - a : a + 1;
  int slice_behind = flip != 0 ? count_a - a + 1 : a;
  float here = density_at(slice_here, b + 1, c + 1);
  bool selected = b >= select_box.x && b <= select_box.y && c >= select_box.z && c <= select_box.w;

  float sa, sb, sc;
  float reach = 0.0;
  if (point) {
    sa = light.x - float(a);
    sb = light.y - float(b);
    sc = light.z - float(c);
    reach = world_length(sa, sb, sc);
    if (lamp_within_slice != 0) {
      /* The lamp lies within one slice: integrate straight to it. */
      float depth = extinction * reach * 0.5 * (here + lamp_density);
      finish(cell, reach > 0.0 ? depth / reach : extinction * lamp_density, exp(-depth), selected);
      return;
    }
    /* One slice back along the ray to the lamp. */
    float per_slice = 1.0 / (float(a) - light.x);
    sa *= per_slice;
    sb *= per_slice;
    sc *= per_slice;
  }
  else {
    /* A sun's direction, one slice back (light.x = -1). */
    sa = light.x;
    sb = light.y;
    sc = light.z;
  }
  float segment_length = world_length(sa, sb, sc);
  float qb = float(b) + sb;
  float qc = float(c) + sc;
  float behind = density_bilinear(slice_behind, qb, qc);
  /* The first slice swept has nothing behind it but the outside (for a sun first_slice = 0,
   * so this is the kernel's `a > first or (not is_point and a > 0)`). */
  float carried = a > first_slice ? previous_bilinear(qb, qc, outside) : outside;
  float segment = extinction * segment_length * 0.5 * (here + behind);
  if (point) {
    float depth = carried * (reach - segment_length) + segment;
    finish(cell, depth / reach, exp(-depth), selected);
  }
  else {
    float value = carried * exp(-segment);
    finish(cell, value, value, selected);
  }
}
