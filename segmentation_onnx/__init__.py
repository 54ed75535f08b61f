"""Gated U-Net training and ONNX export (torch lives only here; extra ``train``).

The trained model file is shipped as package data of this package and run by
``vesselcad.segment`` with onnxruntime.
"""
