"""What a bake hands back: pass images assembled from samples (``images``), gutter
dilation (``dilation``), seam stitching (``seams``), the bake report (``report``) and checks of the results
(``diagnostics``: vertex-mode objects too coarse for their light)."""
