"""``svrnet-mrd``: the streaming core behind the MRD (ISMRMRD) streaming protocol of Gadgetron's
external language interface and Siemens FIRE.

* :mod:`service.mrd.images`: MRD images <-> the core's 2D slices (LPS header geometry -> RAS), and a
  pose as image meta attributes;
* :mod:`service.mrd.connection`: one connection: config, XML header, images in, images with their
  poses and TEXT messages out;
* :mod:`service.mrd.server`: the threaded TCP server and its command line.
"""
