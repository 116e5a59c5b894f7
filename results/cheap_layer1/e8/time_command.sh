set -e
cd /work/main
for i in 1 2 3; do
  ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 .venv/bin/python -m pipelines.studies.cheap_layer1 time --state /work/e8/e4_stages.safetensors --scales 1.0625 --out /work/e8 --name timing_avx2_$i
done
.venv/bin/python -m pipelines.studies.cheap_layer1 time --state /work/e8/e4_stages.safetensors --scales 1.0625 --out /work/e8 --name timing_native_1
