from spconv_cuda_contract import indice_conv  # noqa: F401
