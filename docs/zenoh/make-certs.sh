#!/usr/bin/env bash
# Make a private CA and a certificate for the drone and for the ground, for the TLS configs beside this
# script (onboard-tls.json5, ground-tls.json5). Run it once, on a trusted machine, then copy certs/ca.pem
# with each side's own key and certificate to that side only.
#
#   bash docs/zenoh/make-certs.sh OUT_DIR DRONE_ADDRESS [DRONE_NAME]
#
# DRONE_ADDRESS is the drone's IP on the radio link (the ground checks it against the certificate).
set -euo pipefail
out=${1:?usage: make-certs.sh OUT_DIR DRONE_ADDRESS [DRONE_NAME]}
addr=${2:?usage: make-certs.sh OUT_DIR DRONE_ADDRESS [DRONE_NAME]}
name=${3:-pomar-drone}
days=${DAYS:-365}
mkdir -p "$out"
cd "$out"
umask 077
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -keyout ca.key -out ca.pem \
  -days "$days" -subj "/CN=pomar flight CA" 2>/dev/null
for side in drone ground; do
  if [ "$side" = drone ]; then san="subjectAltName=IP:$addr,DNS:$name"; else san="subjectAltName=DNS:pomar-ground"; fi
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -keyout "$side.key" -out "$side.csr" \
    -subj "/CN=pomar-$side" 2>/dev/null
  printf '%s\nextendedKeyUsage=serverAuth,clientAuth\n' "$san" > "$side.ext"
  openssl x509 -req -in "$side.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$side.pem" -days "$days" \
    -extfile "$side.ext" 2>/dev/null
  rm -f "$side.csr" "$side.ext"
done
echo "certificates in $out: ca.pem (both sides), drone.key + drone.pem (drone only), ground.key + ground.pem (ground only)"
