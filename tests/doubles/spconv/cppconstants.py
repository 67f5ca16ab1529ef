CPU_ONLY_BUILD = False  # the double stands in for a CUDA build
