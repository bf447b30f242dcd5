/* Accumulation of the lighting passes: the sum over light groups and, per group,
 * lighting = rho/pi (E_d + E_g), direct = rho/pi E_d, indirect = rho/pi E_g and
 * irradiance = (E_d + E_g)/pi. Twin of core.lighting.accumulate_passes.
 *
 * irradiance_in (2 * group_count layers) RGBA32F: layer 2g the group's E_d, 2g + 1 its E_g
 * albedo        RGBA32F: rho per sample
 * passes_out    (4 * (1 + group_count) layers) RGBA32F image: layer 4 * slot + pass,
 *               slot 0 the sum of all groups, slot 1 + g group g; pass 0 lighting,
 *               1 direct, 2 indirect, 3 irradiance
 */
const float INV_PI = 0.31830988618379067;

void store_passes(ivec2 cell, int slot, vec3 rho, vec3 direct, vec3 gathered)
{
  vec3 irradiance = direct + gathered;
  imageStore(passes_out, ivec3(cell, 4 * slot + 0), vec4(rho * INV_PI * irradiance, 1.0));
  imageStore(passes_out, ivec3(cell, 4 * slot + 1), vec4(rho * INV_PI * direct, 1.0));
  imageStore(passes_out, ivec3(cell, 4 * slot + 2), vec4(rho * INV_PI * gathered, 1.0));
  imageStore(passes_out, ivec3(cell, 4 * slot + 3), vec4(irradiance * INV_PI, 1.0));
}

void main()
{
  ivec2 cell = ivec2(gl_GlobalInvocationID.xy);
  if (cell.x >= sample_width || cell.y * sample_width + cell.x >= sample_count) {
    return;
  }
  vec3 rho = texelFetch(albedo, cell, 0).rgb;
  vec3 direct_sum = vec3(0.0);
  vec3 gathered_sum = vec3(0.0);
  for (int g = 0; g < group_count; g++) {
    vec3 direct = texelFetch(irradiance_in, ivec3(cell, 2 * g), 0).rgb;
    vec3 gathered = texelFetch(irradiance_in, ivec3(cell, 2 * g + 1), 0).rgb;
    direct_sum += direct;
    gathered_sum += gathered;
    if (per_group != 0) {
      store_passes(cell, 1 + g, rho, direct, gathered);
    }
  }
  store_passes(cell, 0, rho, direct_sum, gathered_sum);
}
