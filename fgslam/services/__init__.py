"""The run's services, peers that the system (:mod:`fgslam.run.system`) owns beside the backend: loop
closure (:mod:`.loops`, with its proximity loops and global BAs in :mod:`.proximity`), the IMU
(:mod:`.imu`, its chain of keys and factors :mod:`.imu_chain`, samples :mod:`.imu_samples`,
initialisation :mod:`.imu_init`, input checks :mod:`.imu_checks`), user factor plugins
(:mod:`.plugins`) and how they move the map (:mod:`.corrections`: the corrections they build, their
route to the contributors that take them). What a service may ask of a frontend is the contributor
contract (:mod:`fgslam.contracts.contributor`); a service reaches a frontend only through it, never
constructs one, and no frontend constructs a service.
"""
