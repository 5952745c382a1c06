#!/bin/sh
# Certificates for a recal fleet with mutual TLS (Zenoh's tls/ links), made with openssl.
#
#   configs/fleet/make-certs.sh DIR ROUTER_HOST NAME...
#
# In DIR (created if missing; nothing is overwritten):
#   ca.pem, ca-key.pem      the fleet CA (kept once; later runs reuse it to sign new names)
#   router.pem, router-key.pem
#                           the router's certificate, subjectAltName ROUTER_HOST (a DNS name
#                           or an IP address): clients connect to tls/ROUTER_HOST:PORT and
#                           check that name
#   NAME.pem, NAME-key.pem  one client certificate per NAME, common name NAME: the router's
#                           access_control matches it (cert_common_names), so give every
#                           gateway, node and operator its own, e.g. gw-a gw-b node-1 operator-1
#
# Private keys are written mode 600. Keep ca-key.pem offline; copy to each machine only its
# own NAME.pem and NAME-key.pem plus ca.pem. Never commit keys. Revoke a client by removing
# its common name from the router's access_control (and restart the router).
set -eu

if [ $# -lt 2 ]; then
    echo "usage: $0 DIR ROUTER_HOST [NAME...]" >&2
    exit 2
fi
dir=$1
router_host=$2
shift 2
days=${RECAL_CERT_DAYS:-825}
mkdir -p "$dir"
umask 077

new_key() {  # EC P-256 private key, PKCS#8 PEM (what rustls reads)
    openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$1" 2>/dev/null
}

sign() {  # sign(name, subject, extensions file)
    openssl req -new -key "$dir/$1-key.pem" -subj "$2" -out "$dir/$1.csr"
    openssl x509 -req -in "$dir/$1.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca-key.pem" \
        -CAcreateserial -days "$days" -sha256 -extfile "$3" -out "$dir/$1.pem" 2>/dev/null
    rm -f "$dir/$1.csr" "$3"
    chmod 644 "$dir/$1.pem"
}

if [ ! -e "$dir/ca.pem" ]; then
    new_key "$dir/ca-key.pem"
    openssl req -x509 -new -key "$dir/ca-key.pem" -subj "/CN=recal fleet CA" -days "$days" \
        -sha256 -addext "basicConstraints=critical,CA:TRUE" \
        -addext "keyUsage=critical,keyCertSign,cRLSign" -out "$dir/ca.pem"
    chmod 644 "$dir/ca.pem"
fi

case $router_host in
    *[!0-9.]*) san="DNS:$router_host" ;;
    *) san="IP:$router_host" ;;
esac
if [ ! -e "$dir/router.pem" ]; then
    new_key "$dir/router-key.pem"
    ext=$(mktemp)
    printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" \
        "extendedKeyUsage=serverAuth,clientAuth" "subjectAltName=$san" > "$ext"
    sign router "/CN=$router_host" "$ext"
fi

for name in "$@"; do
    case $name in
        ""|*[!A-Za-z0-9._-]*) echo "$0: bad name '$name' (letters, digits, . _ -)" >&2; exit 2 ;;
        ca|router) echo "$0: '$name' is taken" >&2; exit 2 ;;
    esac
    [ -e "$dir/$name.pem" ] && continue
    new_key "$dir/$name-key.pem"
    ext=$(mktemp)
    printf '%s\n' "basicConstraints=critical,CA:FALSE" "keyUsage=critical,digitalSignature" \
        "extendedKeyUsage=clientAuth" "subjectAltName=DNS:$name" > "$ext"
    sign "$name" "/CN=$name" "$ext"
done
echo "certificates in $dir: ca.pem router.pem $*"
