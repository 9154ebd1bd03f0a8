"""ROS1 bag format 2.0 at the record level: records and small reads (:mod:`.records`), the index
(:mod:`.index`, with a fast path for the usual layout in :mod:`.usual` and a chunk scan for files
without one in :mod:`.scan`), LZ4 chunk frames (:mod:`.lz4`) and the record encoders (:mod:`.write`).
Nothing here knows about RealSense."""
