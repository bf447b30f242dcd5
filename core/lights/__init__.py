"""What emits light, in Cycles' units: lamps (``lamps``), emissive meshes sampled
directly where the gather would alias (``emitters``), the world through the table's
misses (``environment``), and named lighting setups and sun sweeps (``setups``)."""
