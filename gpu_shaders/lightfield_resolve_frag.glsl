/* One axis of the separable pixel filter (core.lightfield.scene.resolve): target texel
 * (x, y) = sum over taps t of WEIGHTS[t] * source at (x, y) * STEP + t * AXIS, in tap order.
 * TAPS, STEP, AXIS and WEIGHTS are defined at compile time (the loop unrolls). */
void main()
{
  ivec2 first = ivec2(gl_FragCoord.xy) * STEP;
  vec4 sum = vec4(0.0);
  for (int t = 0; t < TAPS; t++) {
    sum += WEIGHTS[t] * texelFetch(source, first + t * AXIS, 0);
  }
  color = sum;
}
