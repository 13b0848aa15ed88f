"""What the learned methods share (PyTorch; importing a module here imports torch, except
:mod:`.config`):

* networks and layers: :mod:`.efficientnet`, :mod:`.resnet` (+ FPN), :mod:`.unet`,
  :mod:`.decoder` (the BEV decoder head), :mod:`.layers`;
* input: :mod:`.inputs` (camera images -> model tensors), :mod:`.bev_warp` (feature maps moved
  between ego poses);
* configuration: :mod:`.config` (``to_dict``/``from_dict`` mix-in, RGB statistics, size bounds);
* weights files: :mod:`.weights` (safetensors reader/writer and checks), :mod:`.mono_weights`
  (the monocular methods' file format), :mod:`.mono_geometry` and :mod:`.mono_mapper` (their
  camera checks and Mapper base);
* running: :mod:`.backends` (ONNX export to onnxruntime / OpenVINO), :mod:`.runtime` (device
  and threads);
* losses: :mod:`.losses`.
"""
