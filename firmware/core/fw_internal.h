/* Shared between fw.c (state, safety, timing) and commands.c (command handlers). */
#ifndef ML_FW_INTERNAL_H
#define ML_FW_INTERNAL_H

#include "fw.h"

/* Zero both outputs, end streams, drop any trial; with `aborted_why` a dropped trial is
 * reported as "ABORTED seq=.. why=..". Every ERR, FAULT, WATCHDOG, STOP, HELLO comes here. */
void fw_zero(fw_t *fw, const char *aborted_why);

/* Recompute code limits and switch the board's attenuators after fw->att_idx[] changed. */
void fw_apply_attenuators(fw_t *fw);

void fw_send_frame(fw_t *fw);                     /* finish fw->tx and send it */
void fw_limit_fault(fw_t *fw); /* report a pending per-sample limit trip: FAULT code=LIMIT */
void fw_begin_event(fw_t *fw, const char *name);  /* next event number into fw->tx */
void fw_send_done(fw_t *fw, int64_t end_us);

/* Reply ERR (zeroes first, as rule 2 demands). */
void fw_err(fw_t *fw, uint16_t seq, const char *code, const char *text);

/* Handle one decoded, valid command. */
void fw_dispatch(fw_t *fw, const command_t *cmd);

#endif
