"""Fringe data sets for learning: the virtual scanner as a training-data generator.

``sim.dataset.config`` (the TOML config) -> ``sim.dataset.objects`` (procedural objects, mesh
folders) -> ``sim.dataset.randomise`` (each sample's scene from (config, seed, index)) ->
``sim.dataset.generate`` (a sample's arrays, traced once for all its patterns) ->
``sim.dataset.store`` (the zarr v3 layout, durable sample writes, the reader ``open``)::

    import sim.dataset

    ds = sim.dataset.open("fringes.zarr")
    sample = ds[0]                         # numpy arrays per camera, and the scene
    batch = ds.batch(ds.indices("train")[:8], ["images", "absolute_phase"])

Names load lazily, so ``import sim.dataset`` is cheap.
"""

from sim._lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, globals(), {
    "config": "DatasetConfig load_config parse_config",
    "randomise": "SampleScene SampleObject draw_scene",
    "generate": "Sample render_sample generate_sample",
    "store": "DatasetReader SampleArrays open write_sample",
})
