"""The run's services, peers that the system (:mod:`fgslam.system`) owns beside the backend: loop
closure (:mod:`.loops`), the IMU (:mod:`.imu`) and user factor plugins (:mod:`.plugins`), and what
they may ask of a frontend (:mod:`.contributor`). A service reaches a frontend only through that
contract; it never constructs one, and no frontend constructs a service.
"""
