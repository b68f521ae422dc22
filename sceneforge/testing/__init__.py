"""What only tests use: writers of the formats sceneforge reads, scene builders, and a
local S3 API (:mod:`.s3`, moto's server) for the object-store tests.

Round trips (write a house in a format, read it back, compare) need writers for SUNCG,
3D-FRONT, glTF, OBJ and PLY; users do not, so they live here rather than in
:mod:`sceneforge.houses.formats` (the sceneforge format's own writer, which the toy houses
use, stays there). No runtime module and no CLI command imports this package
(``tests/test_testing.py`` checks it).
"""
