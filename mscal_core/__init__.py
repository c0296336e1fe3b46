"""mscal_core: the pure maths of field radiometric calibration (Khanna et al., ICRA 2017).

numpy + OpenCV only: no file I/O, no dask, xarray, zarr, rasterio or prefect. One module per
model stage: ``mosaic`` (band layout), ``response`` (Eq. 5-7), ``geometry`` (marker pose and
plane mapping), ``vignetting`` (Eq. 8-10), ``illumination`` (Eq. 11-14, Eq. 16),
``reflectance`` (Eq. 15), and the makers' factory models (``factory``, ``vendors``, ``sunsensor``). The
seeded physical forward model the tests check against lives in :mod:`pipeline.sim.world`.
"""

__version__ = "0.1.0"
