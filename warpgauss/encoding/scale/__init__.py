"""Encoding beyond one device's memory or one process: bricks and their plan (:mod:`.plan`), a
brick's encode and the schedule of the bricks on the devices (:mod:`.bricks`), a joint refit of
the seams (:mod:`.seams`), Dask clusters (:mod:`.cluster`) and the bricked driver
(:mod:`.driver`), which :func:`warpgauss.encode` hands a bricked volume to. The whole-volume path
(:mod:`warpgauss.encoding.driver`) imports nothing from here.
"""
