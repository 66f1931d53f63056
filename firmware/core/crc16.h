/* CRC-16/CCITT-FALSE, the frame checksum of docs/device-protocol.md. */
#ifndef ML_CRC16_H
#define ML_CRC16_H

#include <stddef.h>
#include <stdint.h>

/* poly 0x1021, init 0xFFFF, no reflection, no final xor; "123456789" -> 0x29B1. */
uint16_t crc16_ccitt_false(const void *data, size_t len);

#endif
