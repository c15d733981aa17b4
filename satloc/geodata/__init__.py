"""The geodata layer: georeferenced images and map vectors as they come from outside.

* :mod:`satloc.geodata.georef`: GeoTIFFs, world files and XYZ tile folders read into a
  :class:`~satloc.satmap.SatelliteMap` in one local metric frame (rasterio, pyproj);
* :mod:`satloc.geodata.radiometry`: bit depth, band choice and the stretch to 8-bit RGB;
* :mod:`satloc.geodata.vectors`: road centre lines, building footprints and trees from GeoJSON,
  GeoPackage or Shapefile (pyogrio, shapely).

It may import the data model (:mod:`satloc.errors`, :mod:`satloc.geoframe`, :mod:`satloc.satmap`,
:mod:`satloc.persist`) and nothing of the method's stages nor of :mod:`satloc_env`.
"""
