#!/usr/bin/env bash
# per-suite chain: wait teacher2, distill, AR, copy to shipped, evaluate
set -e
s=$1
cd /work/main
export OMP_NUM_THREADS=1
while [ ! -f ckpt/lib/$s-teacher2.safetensors ] || pgrep -f "out ckpt/lib/$s-teacher2" >/dev/null; do sleep 10; done
D=policies/checkpoints
cp ckpt/lib/$s-teacher2.safetensors $D/libero-$s-bidirectional.safetensors
for ext in json loss.csv loss.png; do cp ckpt/lib/$s-teacher2.$ext $D/libero-$s-bidirectional.$ext; done
date > logs/$s-chain.log
.venv/bin/dvla-harness train --demos demos/libero-$s --recipe distill --teacher $D/libero-$s-bidirectional.safetensors --steps 800 --out $D/libero-$s-fast_dvla.safetensors --quiet >> logs/$s-chain.log 2>&1
date >> logs/$s-chain.log
.venv/bin/dvla-harness train --demos demos/libero-$s --recipe autoregressive --steps 600 --out $D/libero-$s-autoregressive.safetensors --quiet >> logs/$s-chain.log 2>&1
date >> logs/$s-chain.log
.venv-libero/bin/dvla-harness run --suite libero/$s --episodes-per-task 10 \
  --policy bidirectional:checkpoint=libero-$s --policy fast_dllm:checkpoint=libero-$s \
  --policy fast_dvla:checkpoint=libero-$s --policy autoregressive:checkpoint=libero-$s \
  --out runs/libero-$s-10 --overwrite > logs/$s-eval.log 2>&1
date >> logs/$s-chain.log
