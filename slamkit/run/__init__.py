"""Running SLAM: the loop over one shared map (`slam`: SLAM, MappingThread), the I/O around it
(`pipeline`: building the roles, the run outputs), input read-ahead (`prefetch`), the viewer
feed (`viewing`) and returning free heap memory (`heap`)."""
