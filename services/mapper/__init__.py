"""The mapper: online semantic 3D mapping with the paper's three back-ends, and any other.

Library use (no zenoh): `smana.services.mapper.semantic_map.SemanticMap`. The back-ends live in
`backends/`, one module each behind one registry (`backends/__init__.py`): `octree_max.py` and
`octree_bayes.py` (sharing `occupancy.py`), `tsdf.py`; all on the hashed block grid of
`block_grid.py`.
`service.py` is the zenoh wiring; the benchmark is `lab/bench/mapper.py` (`smana bench mapper`).
"""
