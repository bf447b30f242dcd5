/* One triangle covering the target (corners (-1, -1), (3, -1), (-1, 3)), at the far plane
 * (depth 1): drawn with the depth test LESS_EQUAL it shades only what no surface covers. */
void main()
{
  gl_Position = vec4(corner, 1.0, 1.0);
}
