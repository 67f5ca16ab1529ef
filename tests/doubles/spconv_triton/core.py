from spconv_cuda_contract import ConvAlgo  # noqa: F401
