#!/usr/bin/env bash
# The object-store cache against a real S3-compatible server on loopback
# (moto_server, started and stopped here; .ci/run installs it): two batches
# from separate processes, each with its own empty disk cache, share one
# bucket; the second one's frames are all cache hits and its files the same.
#   tests/s3/run.sh PATH/TO/depthgraph
set -euo pipefail
cd "$(dirname "$0")/../.."
bin="$(realpath "${1:?usage: tests/s3/run.sh PATH/TO/depthgraph}")"
work="$(mktemp -d /tmp/depthgraph-s3-test.XXXXXX)"
port="${DEPTHGRAPH_S3_TEST_PORT:-5123}"
moto_server -H 127.0.0.1 -p "$port" >"$work/moto.log" 2>&1 &
moto=$!
# on failure the server's log is shown before the folder goes
trap 'rc=$?; kill $moto 2>/dev/null || true; if [ "$rc" -ne 0 ] && [ -s "$work/moto.log" ]; then echo "moto_server log:"; tail -20 "$work/moto.log"; fi; rm -rf "$work"' EXIT
ready=0
for _ in $(seq 1 300); do
  if curl -sf "http://127.0.0.1:$port/" >/dev/null 2>&1; then ready=1; break; fi
  kill -0 $moto 2>/dev/null || break
  sleep 0.2
done
# (our own server: another one on the port answers too, and ours died)
if [ "$ready" -ne 1 ] || ! kill -0 $moto 2>/dev/null; then
  echo "s3 test: moto_server did not answer on port $port (taken? set DEPTHGRAPH_S3_TEST_PORT)"
  exit 1
fi
curl -sf -X PUT "http://127.0.0.1:$port/depthgraph-cache" >/dev/null
export AWS_ACCESS_KEY_ID=test AWS_SECRET_ACCESS_KEY=test AWS_DEFAULT_REGION=us-east-1
export AWS_ENDPOINT="http://127.0.0.1:$port" AWS_ALLOW_HTTP=true
export DEPTHGRAPH_BACKEND=cpu
unset DEPTHGRAPH_FAULT_TRANSIENT
url="s3://depthgraph-cache/runs/seq"
small=(--set scene.width=64 --set scene.height=48 --set refocus.samples=16)

"$bin" batch graphs/sequence_demo.ron --frames 0..12 --out "$work/a" --cache-dir "$work/cache_a" \
  --cache-url "$url" --quiet "${small[@]}" 2>"$work/a.err" || { cat "$work/a.err"; exit 1; }
grep -q '12 done (12 computed, 0 from cache)' "$work/a.err" || { cat "$work/a.err"; exit 1; }
"$bin" batch graphs/sequence_demo.ron --frames 0..12 --out "$work/b" --cache-dir "$work/cache_b" \
  --cache-url "$url" --quiet "${small[@]}" 2>"$work/b.err" || { cat "$work/b.err"; exit 1; }
grep -q '12 done (0 computed, 12 from cache)' "$work/b.err" || { cat "$work/b.err"; exit 1; }
test "$(grep -c '"status":"cached"' "$work/b/manifest.jsonl")" -eq 12
(cd "$work/a/frames" && sha256sum ./*.png) >"$work/a.sum"
(cd "$work/b/frames" && sha256sum ./*.png) >"$work/b.sum"
diff "$work/a.sum" "$work/b.sum"
# a store that does not answer is a transient failure before anything runs
set +e
AWS_ENDPOINT="http://127.0.0.1:9" "$bin" batch graphs/sequence_demo.ron --frames 0..2 --out "$work/c" \
  --cache-url "$url" --quiet "${small[@]}" 2>"$work/c.err"
rc=$?
set -e
test "$rc" -eq 75 || { echo "expected exit 75, got $rc"; cat "$work/c.err"; exit 1; }
# a bucket that does not exist is a usage error (the probe's write finds
# no bucket; a read alone took the answer for a cache miss and ran on)
set +e
"$bin" batch graphs/sequence_demo.ron --frames 0..2 --out "$work/d" \
  --cache-url "s3://no-such-bucket/x" --quiet "${small[@]}" 2>"$work/d.err"
rc=$?
set -e
test "$rc" -eq 2 || { echo "expected exit 2 for a missing bucket, got $rc"; cat "$work/d.err"; exit 1; }
grep -q 'refuses' "$work/d.err" || { cat "$work/d.err"; exit 1; }
test ! -e "$work/d/manifest.jsonl"
echo "s3 test: passed (12 frames shared through $url on moto_server)"
