/* A light field view's triangles: positions relative to the scene's centre (the matrix
 * moves them back in float64 on the CPU, so a scene far from the origin keeps its precision). */
void main()
{
  gl_Position = view_projection * vec4(position, 1.0);
#ifdef TEXTURED
  v_uv = uv;
#endif
  v_radiance = radiance;
}
