"""The ground station's browser page (``olsplat ground web``): what it shows is made by pure
functions (``splats``), read from a finished run or asked over the ground link (``review``), and
drawn by a thin viser page (``page``)."""
