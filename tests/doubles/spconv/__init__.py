"""A test double standing in for spconv (see ../spconv_cuda_contract.py); never on sys.path outside the tests."""
