/* One pass of gutter dilation: the twin of a loop iteration of core.raster.dilate.
 *
 * Every still-empty texel with at least one filled 8-neighbour takes the mean of those
 * neighbours and counts as filled in the next pass. Passes ping-pong between two pairs
 * of textures, so every invocation sees the state before this pass, as numpy's fancy
 * indexing does; every texel is written, so the target never keeps a stale value.
 *
 * source_values / target_values (channel layers) RGBA32F: 4 image channels a layer;
 *             texels not yet filled hold exactly 0 (numpy's zero-initialised values)
 * source_known / target_known   R32F: 1 where covered or filled, 0 elsewhere
 * single_channel  1 when the image has one channel (numpy sums in another order then)
 *
 * Dispatch: x, y over texels, z over channel layers; layer 0 writes the mask.
 */

/* Without `precise` Mesa reassociates the sums below (seen on llvmpipe: 1 ulp off numpy
 * with one channel). MSL has no such qualifier; Blender's Metal backend is untested. */
#ifdef GPU_METAL
#  define PRECISE
#else
#  define PRECISE precise
#endif

/* numpy's _neighbours8 order: the sum below depends on it. */
const ivec2 neighbour_offsets[8] = ivec2[8](ivec2(-1, -1), ivec2(0, -1), ivec2(1, -1),
                                            ivec2(-1, 0), ivec2(1, 0),
                                            ivec2(-1, 1), ivec2(0, 1), ivec2(1, 1));

void main()
{
  ivec3 cell = ivec3(gl_GlobalInvocationID);
  ivec2 size = textureSize(source_known, 0);
  if (cell.x >= size.x || cell.y >= size.y) {
    return;
  }
  PRECISE vec4 value = texelFetch(source_values, cell, 0);
  bool known = texelFetch(source_known, cell.xy, 0).r > 0.5;
  if (!known) {
    vec4 terms[8];
    int count = 0;
    for (int n = 0; n < 8; n++) {
      ivec2 at = cell.xy + neighbour_offsets[n];
      bool inside = all(greaterThanEqual(at, ivec2(0))) && all(lessThan(at, size));
      /* numpy clamps outside neighbours into the image and multiplies their value by a
       * zero weight; doing the same keeps its results for non-finite inputs (0 * inf). */
      ivec2 clamped = clamp(at, ivec2(0), size - 1);
      float weight = (inside && texelFetch(source_known, clamped, 0).r > 0.5) ? 1.0 : 0.0;
      terms[n] = weight * texelFetch(source_values, ivec3(clamped, cell.z), 0);
      count += int(weight);
    }
    if (count > 0) {
      /* The summation order of numpy's einsum("fn,fnc->fc") (numpy 1.26, x86-64): with
       * several channels it adds the 8 terms one after the other; with one channel the
       * reduced axis is contiguous and it sums 4-wide SIMD lanes (n, n + 4), then the
       * lanes pairwise. Zero terms (weight 0) add exactly, so only the order of the
       * filled neighbours matters, and matching it makes the sums identical. */
      PRECISE vec4 total;
      if (single_channel != 0) {
        total = ((terms[0] + terms[4]) + (terms[1] + terms[5])) +
                ((terms[2] + terms[6]) + (terms[3] + terms[7]));
      }
      else {
        total = vec4(0.0);
        for (int n = 0; n < 8; n++) {
          total += terms[n];
        }
      }
      /* numpy divides in float64 and rounds to float32, which equals a correctly
       * rounded float32 division (double rounding is harmless for division). */
      value = total / float(count);
      known = true;
    }
  }
  imageStore(target_values, cell, value);
  if (cell.z == 0) {
    imageStore(target_known, cell.xy, vec4(known ? 1.0 : 0.0));
  }
}
