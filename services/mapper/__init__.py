"""The mapper: online semantic 3D mapping with the paper's three back-ends.

Library use (no zenoh): `smana.services.mapper.semantic_map.SemanticMap`. The back-ends live in
`octree.py` (octree-max, octree-bayes) and `tsdf.py`, on the hashed block grid of `_grid.py`;
`service.py` is the zenoh wiring; the benchmark is `lab/bench/mapper.py` (`smana bench mapper`).
"""
