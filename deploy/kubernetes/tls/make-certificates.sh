#!/bin/sh
# The fleet's TLS: a CA and one certificate for the routers, naming every router by the name the cluster
# uses for it (docs/kubernetes.md "TLS"). Explicit names only: rustls, which zenoh uses, refuses a wildcard
# over one label (*.gcdtrav-router), so nothing would connect.
#   deploy/kubernetes/tls/make-certificates.sh OUT_DIR [PUBLIC_NAME...]
# ROUTERS (default "gcdtrav-router-0 gcdtrav-router-1": the StatefulSet's pods, as in router.yaml) and
# NAMESPACE (default gcdtrav) say which names to write; each PUBLIC_NAME is an address robots use
# (DNS name, or an IP address as IP:203.0.113.7). Writes OUT_DIR/{ca.crt,ca.key,tls.crt,tls.key}; keep
# ca.key offline. Then: kubectl -n gcdtrav create secret generic gcdtrav-tls \
#     --from-file=OUT_DIR/tls.crt --from-file=OUT_DIR/tls.key --from-file=OUT_DIR/ca.crt
set -eu
out=${1:?usage: make-certificates.sh OUT_DIR [PUBLIC_NAME...]}
shift
routers=${ROUTERS:-"gcdtrav-router-0 gcdtrav-router-1"}
namespace=${NAMESPACE:-gcdtrav}
days=${DAYS:-365}
names=""
for router in $routers; do  # the pods connect by the short name; the longer ones for other namespaces
    names="$names,DNS:$router.gcdtrav-router,DNS:$router.gcdtrav-router.$namespace.svc"
    names="$names,DNS:$router.gcdtrav-router.$namespace.svc.cluster.local"
done
names="$names,DNS:gcdtrav-router-public,DNS:gcdtrav-router-public.$namespace.svc"
for public in "$@"; do
    case $public in
        IP:*) names="$names,$public" ;;
        *) names="$names,DNS:$public" ;;
    esac
done
mkdir -p "$out"
cd "$out"
[ -f ca.key ] || openssl req -x509 -newkey rsa:2048 -nodes -days 3650 -subj "/CN=gcdtrav-ca" \
    -keyout ca.key -out ca.crt 2>/dev/null
openssl req -newkey rsa:2048 -nodes -subj "/CN=gcdtrav-router" -keyout tls.key -out tls.csr 2>/dev/null
printf "subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\n" "${names#,}" > tls.ext
openssl x509 -req -in tls.csr -CA ca.crt -CAkey ca.key -CAcreateserial -days "$days" -extfile tls.ext \
    -out tls.crt 2>/dev/null
rm -f tls.csr tls.ext
echo "$out/tls.crt names: ${names#,}"
