#!/bin/sh
# Make a lab CA and the certificates posecal's Zenoh links need (TLS, mutual TLS).
#
#   deploy/make-lab-ca.sh [options] DIR [AGENT ...]
#
# In DIR (created, mode 700):
#   ca.pem, ca-key.pem            the lab CA (made once; reused on later runs)
#   SERVICE.pem, SERVICE-key.pem  the service's (or a router's) certificate: CN = SERVICE,
#                                 subjectAltName = the --hosts names and addresses
#   AGENT.pem, AGENT-key.pem      one per capture agent: CN = AGENT, client use only.
#                                 Name agents <rig>-<camera> (lab-c0): the CN is what the
#                                 service's access rules (POSECAL_ZENOH_AGENTS) match.
#
# Options:
#   --hosts H1,H2,...  names and IP addresses the agents use to reach the service
#                      (default: localhost,127.0.0.1); Zenoh checks the name it connects to
#   --service NAME     CN and file name of the service certificate (default: service)
#   --days N           validity of new certificates (default: 825; the CA: 3650)
#   --renew            re-issue the certificates named on this run even if they are valid
#   --new-ca           replace an existing CA (every certificate it signed stops working;
#                      all certificates named on this run are re-issued)
#
# Re-running is safe: the CA is never replaced without --new-ca, and a certificate that
# exists and verifies against the CA is kept (the service's too, unless its host names
# changed). Keys are EC P-256 (PKCS#8), made with openssl only.
set -eu

usage() { sed -n '2,27p' "$0" | sed 's/^# \{0,1\}//' >&2; exit 2; }
die() { echo "make-lab-ca: $*" >&2; exit 1; }

hosts=localhost,127.0.0.1
service=service
days=825
renew=0
new_ca=0
while [ $# -gt 0 ]; do
  case $1 in
    --hosts) [ $# -ge 2 ] || usage; hosts=$2; shift 2 ;;
    --hosts=*) hosts=${1#*=}; shift ;;
    --service) [ $# -ge 2 ] || usage; service=$2; shift 2 ;;
    --service=*) service=${1#*=}; shift ;;
    --days) [ $# -ge 2 ] || usage; days=$2; shift 2 ;;
    --days=*) days=${1#*=}; shift ;;
    --renew) renew=1; shift ;;
    --new-ca) new_ca=1; shift ;;
    -h|--help) usage ;;
    --) shift; break ;;
    -*) echo "make-lab-ca: unknown option $1" >&2; usage ;;
    *) break ;;
  esac
done
[ $# -ge 1 ] || usage
dir=$1
shift

command -v openssl >/dev/null 2>&1 || die "openssl is not installed (apt-get install openssl)"
case $days in ''|*[!0-9]*) die "--days needs a number of days, got '$days'" ;; esac
check_name() {
  case $1 in
    ''|*[!A-Za-z0-9_.-]*|.*) die "certificate names are letters, digits, '_', '.' and '-', got '$1'" ;;
  esac
  [ "$1" != ca ] || die "'ca' is the CA's file name; name the certificate otherwise"
}
check_name "$service"
for agent in "$@"; do
  check_name "$agent"
  [ "$agent" != "$service" ] || die "agent '$agent' has the service's name"
done

# subjectAltName from --hosts: addresses as IP:, names as DNS:.
san=""
old_ifs=$IFS
IFS=,
for h in $hosts; do
  [ -n "$h" ] || continue
  case $h in
    *[!0-9.]*) case $h in *:*) entry="IP:$h" ;; *) entry="DNS:$h" ;; esac ;;
    *) entry="IP:$h" ;;
  esac
  san="${san:+$san,}$entry"
done
IFS=$old_ifs
[ -n "$san" ] || die "--hosts names no host"

umask 077
mkdir -p "$dir"
chmod 700 "$dir"
tmp=$(mktemp -d "${TMPDIR:-/tmp}/make-lab-ca.XXXXXX")
trap 'rm -rf "$tmp"' EXIT INT TERM

ca="$dir/ca.pem"
ca_key="$dir/ca-key.pem"

if [ -e "$ca" ] || [ -e "$ca_key" ]; then
  if [ "$new_ca" -eq 0 ]; then
    [ -f "$ca" ] && [ -f "$ca_key" ] || die "$dir holds only half a CA (ca.pem or ca-key.pem); pass --new-ca to replace it"
    echo "kept the CA $ca"
  fi
fi
if [ ! -e "$ca" ] || [ "$new_ca" -eq 1 ]; then
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$tmp/ca-key.pem" 2>/dev/null
  cat >"$tmp/ca.cnf" <<EOF
[req]
distinguished_name = dn
prompt = no
x509_extensions = v3_ca
[dn]
CN = posecal lab CA
[v3_ca]
basicConstraints = critical, CA:TRUE, pathlen:0
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
EOF
  openssl req -new -x509 -key "$tmp/ca-key.pem" -config "$tmp/ca.cnf" -days 3650 -sha256 \
    -out "$tmp/ca.pem"
  mv "$tmp/ca-key.pem" "$ca_key"
  mv "$tmp/ca.pem" "$ca"
  renew=1  # a new CA: every certificate named on this run is re-issued
  echo "made the CA $ca (keep $ca_key off the camera hosts)"
fi

# issue NAME USAGE [SAN]: NAME.pem / NAME-key.pem signed by the CA.
issue() {
  name=$1 usage=$2 alt=${3:-}
  cert="$dir/$name.pem" key="$dir/$name-key.pem"
  if [ "$renew" -eq 0 ] && [ -f "$cert" ] && [ -f "$key" ] \
      && openssl verify -CAfile "$ca" "$cert" >/dev/null 2>&1; then
    if [ -z "$alt" ] || names_hosts "$cert"; then
      echo "kept $cert"
      return
    fi
  fi
  openssl genpkey -algorithm EC -pkeyopt ec_paramgen_curve:P-256 -out "$tmp/$name-key.pem" 2>/dev/null
  openssl req -new -key "$tmp/$name-key.pem" -subj "/CN=$name" -out "$tmp/$name.csr"
  {
    echo "basicConstraints = critical, CA:FALSE"
    echo "keyUsage = critical, digitalSignature"
    echo "extendedKeyUsage = $usage"
    echo "subjectKeyIdentifier = hash"
    echo "authorityKeyIdentifier = keyid"
    [ -z "$alt" ] || echo "subjectAltName = $alt"
  } >"$tmp/$name.ext"
  openssl x509 -req -in "$tmp/$name.csr" -CA "$ca" -CAkey "$ca_key" -CAcreateserial \
    -CAserial "$tmp/ca.srl" -days "$days" -sha256 -extfile "$tmp/$name.ext" -out "$tmp/$name.pem" 2>/dev/null
  mv "$tmp/$name-key.pem" "$key"
  mv "$tmp/$name.pem" "$cert"
  echo "made $cert (CN=$name${alt:+, $alt})"
}

# Whether a certificate names exactly the --hosts (openssl compares, so 0:0::1 is ::1).
names_hosts() {
  printed=$(openssl x509 -in "$1" -noout -ext subjectAltName 2>/dev/null | sed -n '2,$p')
  [ "$(echo "$printed" | tr ',' '\n' | grep -c ':')" -eq "$(echo "$san" | tr ',' '\n' | grep -c ':')" ] || return 1
  old_ifs=$IFS
  IFS=,
  for entry in $san; do
    case $entry in
      IP:*) check="-checkip ${entry#IP:}" ;;
      *) check="-checkhost ${entry#DNS:}" ;;
    esac
    IFS=$old_ifs
    # shellcheck disable=SC2086  # check is an option and its value
    openssl x509 -in "$1" -noout $check | grep -q ' does match ' || return 1
    IFS=,
  done
  IFS=$old_ifs
}

issue "$service" "serverAuth, clientAuth" "$san"
for agent in "$@"; do
  issue "$agent" "clientAuth"
done
chmod 600 "$dir"/*-key.pem
chmod 644 "$dir"/ca.pem "$dir/$service.pem"
for agent in "$@"; do chmod 644 "$dir/$agent.pem"; done
