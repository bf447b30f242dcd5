"""Light fields in the HCI 4D benchmark layout: the camera grid (``cameras``) and its files (``hci``)."""
