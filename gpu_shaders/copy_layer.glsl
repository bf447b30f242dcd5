/* Copy one layer of an array texture into a 2D image: GPUTexture.read() returns only
 * layer 0 of an array texture, so every other layer is read back through this. */
void main()
{
  ivec2 cell = ivec2(gl_GlobalInvocationID.xy);
  ivec3 size = textureSize(source, 0);
  if (cell.x >= size.x || cell.y >= size.y) {
    return;
  }
  imageStore(target, cell, texelFetch(source, ivec3(cell, layer), 0));
}
