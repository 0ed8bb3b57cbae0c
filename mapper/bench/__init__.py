"""What ``govnesf bench`` needs from the mapper side, shipped in the package (the bench is a client
and never imports ``mapper``: it runs these modules with ``python -m``)."""
